//! `detect.hough_circles`: circles by the Hough gradient method (OpenCV's `HOUGH_GRADIENT`),
//! with sub-pixel centres and radii.
//!
//! [`hough_circles`] works on a gray 8-bit image:
//! 1. optional Gaussian pre-blur;
//! 2. Canny edges ([`canny`], thresholds `high/2`, `high`) of the blurred image and its 3×3
//!    Sobel gradients at the edge pixels;
//! 3. every edge pixel votes along its gradient line, both ways, for radii in the search range,
//!    into a centre accumulator with cells of `dp × dp` px (fixed-point ray stepping, 16
//!    fractional bits);
//! 4. centres: accumulator cells with more than `votes_threshold` votes that are 4-neighbourhood
//!    maxima (OpenCV's rule), strongest first, at least `min_dist` apart;
//! 5. radius per centre: a histogram of the distances of the edge pixels whose gradient points
//!    at the centre, its best 3-px window by support per unit radius;
//! 6. refinement: the edge pixels near that circle are located to sub-pixel accuracy (parabola
//!    through the gradient magnitude across the edge, as Devernay's sub-pixel Canny), split by
//!    polarity, and each polarity fitted by an algebraic (Kåsa) circle then Gauss–Newton
//!    iterations of the geometric fit; two opposite edges of a drawn line give its middle.
//!
//! # Determinism
//!
//! Voting runs in parallel over fixed bands of accumulator rows: each band walks every ray but
//! only over the radius interval (computed exactly in integers) that falls inside the band, so a
//! cell's count is the same integer whatever the thread count. Peak search runs on fixed row
//! bands whose peak lists are concatenated in band order; each centre's radius estimate and fit
//! is an independent sequential computation. Results are bit-identical for any thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Matrix, Value};
use rayon::prelude::*;

use super::canny::canny;
use super::gray::gray_u8;
use crate::filter::border::BorderMode;
use crate::filter::gaussian::gaussian_blur;

/// Fractional bits of the fixed-point ray positions.
const SHIFT: u32 = 16;
/// 1.0 in fixed point.
const ONE: f64 = (1u64 << SHIFT) as f64;
/// Accumulator rows per parallel voting / peak-search band.
const BAND_ROWS: usize = 32;
/// Smallest radius searched, px: below it the edge ring of a disc is not a circle.
const MIN_SEARCH_RADIUS: f64 = 2.0;
/// An edge pixel supports a centre when its gradient is within acos(0.9) ≈ 26° of the line to
/// the centre (either way).
const RADIAL_COS: f64 = 0.9;
/// Half-width of the band of edge pixels used by the final fits, px.
const FIT_BAND: f64 = 1.5;
/// Largest distance between the two edges of a line drawn as a circle, px: two fitted edges of
/// opposite polarity this close are reported as one circle at their middle.
const MAX_LINE_WIDTH: f64 = 6.0;
/// Centres refined per parallel batch.
const CENTRE_BATCH: usize = 32;
/// Largest accepted accumulator (cells).
const MAX_CELLS: usize = 1 << 28;
/// `tan 22.5°`, the sector limit of the sub-pixel step direction.
const TAN_22_5: f32 = 0.414_213_56;

/// Options of [`hough_circles`]; see [`HoughCirclesParams`] for their meaning.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CircleOptions {
    /// Accumulator cell size, px (≥ 1).
    pub dp: f64,
    /// Smallest distance between reported centres, px.
    pub min_dist: f64,
    /// Canny's upper threshold (the lower one is half of it).
    pub canny_high: f64,
    /// Accumulator votes (and radius support) a circle needs, strictly exceeded.
    pub votes_threshold: u32,
    /// Smallest radius, px.
    pub min_radius: f64,
    /// Largest radius, px (0: the image diagonal).
    pub max_radius: f64,
    /// Largest number of circles (0: all).
    pub max_circles: usize,
    /// Standard deviation of the Gaussian pre-blur, px (0: none).
    pub sigma: f64,
}

impl Default for CircleOptions {
    fn default() -> Self {
        CircleOptions {
            dp: 1.0,
            min_dist: 20.0,
            canny_high: 100.0,
            votes_threshold: 30,
            min_radius: 0.0,
            max_radius: 0.0,
            max_circles: 0,
            sigma: 1.0,
        }
    }
}

/// One detected circle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Circle {
    /// Centre column, px (pixel centres at integers).
    pub x: f64,
    /// Centre row, px.
    pub y: f64,
    /// Radius, px.
    pub radius: f64,
    /// Votes of the accumulator peak.
    pub votes: u32,
}

/// An edge pixel with its unit gradient.
#[derive(Debug, Clone, Copy)]
struct EdgePoint {
    x: i32,
    y: i32,
    ux: f32,
    uy: f32,
}

/// The edge pixels in raster order and where each row starts.
struct Edges<'a> {
    points: Vec<EdgePoint>,
    /// `points[row_start[y]..row_start[y + 1]]` are row y's.
    row_start: Vec<usize>,
    gray: &'a [u8],
    width: usize,
    height: usize,
}

/// The 3×3 Sobel gradient of `gray` at (x, y), border replicate (as [`canny`]'s).
fn sobel_at(gray: &[u8], width: usize, height: usize, x: usize, y: usize) -> (i32, i32) {
    let (xl, xr) = (x.saturating_sub(1), (x + 1).min(width - 1));
    let (ru, rd) = (y.saturating_sub(1) * width, (y + 1).min(height - 1) * width);
    let rc = y * width;
    let at = |r: usize, c: usize| i32::from(gray[r + c]);
    let gx = at(ru, xr) + 2 * at(rc, xr) + at(rd, xr) - at(ru, xl) - 2 * at(rc, xl) - at(rd, xl);
    let gy = at(rd, xl) + 2 * at(rd, x) + at(rd, xr) - at(ru, xl) - 2 * at(ru, x) - at(ru, xr);
    (gx, gy)
}

impl Edges<'_> {
    fn magnitude(&self, x: i32, y: i32) -> Option<f32> {
        if x < 0 || y < 0 || x as usize >= self.width || y as usize >= self.height {
            return None;
        }
        let (gx, gy) = sobel_at(self.gray, self.width, self.height, x as usize, y as usize);
        Some((gx as f32).hypot(gy as f32))
    }

    /// Sub-pixel position of edge pixel `p`: the vertex of the parabola through the gradient
    /// magnitudes at `p` and its two neighbours along the gradient's 45° sector (Devernay 1995).
    /// The pixel itself when a neighbour is outside or the magnitude is not a strict peak.
    fn subpixel(&self, p: &EdgePoint) -> (f64, f64) {
        let (ax, ay) = (p.ux.abs(), p.uy.abs());
        let (sx, sy) = if ay <= TAN_22_5 * ax {
            (1, 0)
        } else if ax <= TAN_22_5 * ay {
            (0, 1)
        } else if (p.ux > 0.0) == (p.uy > 0.0) {
            (1, 1)
        } else {
            (1, -1)
        };
        let here = (f64::from(p.x), f64::from(p.y));
        let (Some(m0), Some(minus), Some(plus)) = (
            self.magnitude(p.x, p.y),
            self.magnitude(p.x - sx, p.y - sy),
            self.magnitude(p.x + sx, p.y + sy),
        ) else {
            return here;
        };
        let denom = f64::from(minus) - 2.0 * f64::from(m0) + f64::from(plus);
        if denom >= 0.0 {
            return here;
        }
        let eta = (0.5 * f64::from(minus - plus) / denom).clamp(-0.5, 0.5);
        (here.0 + eta * f64::from(sx), here.1 + eta * f64::from(sy))
    }

    /// Edge pixels whose gradient points at `(cx, cy)` or away from it (within acos
    /// [`RADIAL_COS`]) at a distance in `[lo, hi]`, with that distance and whether the
    /// gradient points away (outwards).
    fn radial(&self, cx: f64, cy: f64, lo: f64, hi: f64, mut f: impl FnMut(&EdgePoint, f64, bool)) {
        if self.height == 0 {
            return;
        }
        let y0 = (cy - hi).floor().max(0.0) as usize;
        let y1 = ((cy + hi).ceil().max(0.0) as usize).min(self.height - 1);
        let (x0, x1) = ((cx - hi).floor(), (cx + hi).ceil());
        let (lo2, hi2) = (lo * lo, hi * hi);
        for y in y0..=y1 {
            let row = &self.points[self.row_start[y]..self.row_start[y + 1]];
            let start = row.partition_point(|p| f64::from(p.x) < x0);
            for p in &row[start..] {
                if f64::from(p.x) > x1 {
                    break;
                }
                let (vx, vy) = (f64::from(p.x) - cx, f64::from(p.y) - cy);
                let d2 = vx * vx + vy * vy;
                if d2 < lo2 || d2 > hi2 || d2 == 0.0 {
                    continue;
                }
                let d = d2.sqrt();
                let dot = vx * f64::from(p.ux) + vy * f64::from(p.uy);
                if dot.abs() >= RADIAL_COS * d {
                    f(p, d, dot > 0.0);
                }
            }
        }
    }
}

/// Canny edges and unit gradients of `gray`.
fn edges_of(gray: &[u8], width: usize, height: usize, high: f64) -> Edges<'_> {
    let edge_map = canny(gray, width, height, high * 0.5, high, 3, false);
    let mut points = Vec::new();
    let mut row_start = Vec::with_capacity(height + 1);
    for y in 0..height {
        row_start.push(points.len());
        let row = &edge_map[y * width..(y + 1) * width];
        for (x, _) in row.iter().enumerate().filter(|(_, e)| **e != 0) {
            let (gx, gy) = sobel_at(gray, width, height, x, y);
            let (gx, gy) = (gx as f32, gy as f32);
            let m = gx.hypot(gy);
            if m > 0.0 {
                points.push(EdgePoint {
                    x: x as i32,
                    y: y as i32,
                    ux: gx / m,
                    uy: gy / m,
                });
            }
        }
    }
    row_start.push(points.len());
    Edges {
        points,
        row_start,
        gray,
        width,
        height,
    }
}

/// `floor(a / b)` for `b ≠ 0`.
fn floor_div(a: i64, b: i64) -> i64 {
    if b < 0 {
        (-a).div_euclid(-b)
    } else {
        a.div_euclid(b)
    }
}

/// The integer `r` interval with `lo ≤ p + r·s ≤ hi` (empty when the first bound exceeds the
/// second).
fn ray_interval(p: i64, s: i64, lo: i64, hi: i64) -> (i64, i64) {
    match s.signum() {
        0 if (lo..=hi).contains(&p) => (i64::MIN / 4, i64::MAX / 4),
        0 => (1, 0),
        1 => (-floor_div(p - lo, s), floor_div(hi - p, s)),
        _ => (-floor_div(p - hi, s), floor_div(lo - p, s)),
    }
}

/// A ray in fixed point: the pixel's accumulator position (+1 for the frame) and its step per
/// px of radius.
#[derive(Clone, Copy)]
struct Ray {
    x0: i64,
    y0: i64,
    sx: i64,
    sy: i64,
}

/// The part of a ray inside the accumulator and the radius range: `len` steps from `(x, y)`,
/// over accumulator rows `row_lo..=row_hi`.
#[derive(Clone, Copy)]
struct Segment {
    x: i64,
    y: i64,
    sx: i64,
    sy: i64,
    len: i64,
    row_lo: i64,
    row_hi: i64,
}

/// The centre accumulator (with a one-cell zero frame) of the edge rays, both ways, over radii
/// `rmin..=rmax`; a ray stops where it leaves the accumulator.
fn vote(rays: &[Ray], cols: usize, rows: usize, rmin: i64, rmax: i64) -> Vec<u32> {
    let stride = cols + 2;
    let mut acc = vec![0u32; stride * (rows + 2)];
    let one = 1i64 << SHIFT;
    let (xlo, xhi) = (one, (cols as i64 + 1) * one - 1);
    let (ylo, yhi) = (one, (rows as i64 + 1) * one - 1);
    let mut segments = Vec::with_capacity(rays.len() * 2);
    for ray in rays {
        for sign in [1i64, -1] {
            let (sx, sy) = (ray.sx * sign, ray.sy * sign);
            let (ya, yb) = ray_interval(ray.y0, sy, ylo, yhi);
            let (xa, xb) = ray_interval(ray.x0, sx, xlo, xhi);
            let ra = ya.max(xa).max(rmin);
            let rb = yb.min(xb).min(rmax);
            if ra > rb {
                continue;
            }
            let (y, y_end) = (ray.y0 + ra * sy, ray.y0 + rb * sy);
            segments.push(Segment {
                x: ray.x0 + ra * sx,
                y,
                sx,
                sy,
                len: rb - ra + 1,
                row_lo: y.min(y_end) >> SHIFT,
                row_hi: y.max(y_end) >> SHIFT,
            });
        }
    }
    acc.par_chunks_mut(stride * BAND_ROWS)
        .enumerate()
        .for_each(|(b, band)| {
            let b0 = (b * BAND_ROWS) as i64;
            let b1 = b0 + (band.len() / stride) as i64 - 1;
            for seg in &segments {
                if seg.row_hi < b0 || seg.row_lo > b1 {
                    continue;
                }
                let (ta, tb) = if seg.row_lo >= b0 && seg.row_hi <= b1 {
                    (0, seg.len - 1)
                } else {
                    let (ta, tb) = ray_interval(seg.y, seg.sy, b0 * one, (b1 + 1) * one - 1);
                    (ta.max(0), tb.min(seg.len - 1))
                };
                let mut x = seg.x + ta * seg.sx;
                let mut y = seg.y + ta * seg.sy - b0 * one;
                for _ in ta..=tb {
                    band[(y >> SHIFT) as usize * stride + (x >> SHIFT) as usize] += 1;
                    x += seg.sx;
                    y += seg.sy;
                }
            }
        });
    acc
}

/// Accumulator cells (padded index) with more than `threshold` votes that are > their left and
/// upper neighbours and ≥ their right and lower ones, strongest first (ties: raster order).
fn peaks(acc: &[u32], cols: usize, rows: usize, threshold: u32) -> Vec<(u32, usize)> {
    let stride = cols + 2;
    let bands: Vec<Vec<(u32, usize)>> = (0..rows.div_ceil(BAND_ROWS))
        .into_par_iter()
        .map(|b| {
            let mut found = Vec::new();
            for j in b * BAND_ROWS..((b + 1) * BAND_ROWS).min(rows) {
                let base = (j + 1) * stride;
                for i in 1..=cols {
                    let k = base + i;
                    let v = acc[k];
                    if v > threshold
                        && v > acc[k - 1]
                        && v >= acc[k + 1]
                        && v > acc[k - stride]
                        && v >= acc[k + stride]
                    {
                        found.push((v, k));
                    }
                }
            }
            found
        })
        .collect();
    let mut all: Vec<(u32, usize)> = bands.into_iter().flatten().collect();
    all.sort_unstable_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
    all
}

/// Points kept at least `min_dist` apart, in a uniform grid of buckets.
struct Spacing {
    min_dist: f64,
    cell: f64,
    buckets: std::collections::HashMap<(i64, i64), Vec<(f64, f64)>>,
}

impl Spacing {
    fn new(min_dist: f64) -> Spacing {
        Spacing {
            min_dist,
            cell: min_dist.max(1.0),
            buckets: std::collections::HashMap::new(),
        }
    }

    fn key(&self, x: f64, y: f64) -> (i64, i64) {
        (
            (x / self.cell).floor() as i64,
            (y / self.cell).floor() as i64,
        )
    }

    /// Whether (x, y) is at least `min_dist` from every inserted point.
    fn free(&self, x: f64, y: f64) -> bool {
        let (kx, ky) = self.key(x, y);
        let d2 = self.min_dist * self.min_dist;
        for gy in ky - 1..=ky + 1 {
            for gx in kx - 1..=kx + 1 {
                if let Some(pts) = self.buckets.get(&(gx, gy))
                    && pts
                        .iter()
                        .any(|&(px, py)| (px - x).powi(2) + (py - y).powi(2) < d2)
                {
                    return false;
                }
            }
        }
        true
    }

    fn insert(&mut self, x: f64, y: f64) {
        let k = self.key(x, y);
        self.buckets.entry(k).or_default().push((x, y));
    }
}

/// Solves the symmetric 3×3 system `a·v = b` by Gaussian elimination with partial pivoting;
/// `None` when (nearly) singular.
fn solve3(mut a: [[f64; 3]; 3], mut b: [f64; 3]) -> Option<[f64; 3]> {
    let scale = a
        .iter()
        .flatten()
        .fold(0.0f64, |m, v| m.max(v.abs()))
        .max(f64::MIN_POSITIVE);
    for c in 0..3 {
        let p = (c..3).max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))?;
        if a[p][c].abs() <= 1e-12 * scale {
            return None;
        }
        a.swap(c, p);
        b.swap(c, p);
        let pivot = a[c];
        for r in c + 1..3 {
            let f = a[r][c] / pivot[c];
            for (dst, src) in a[r].iter_mut().zip(pivot).skip(c) {
                *dst -= f * src;
            }
            b[r] -= f * b[c];
        }
    }
    let mut v = [0.0; 3];
    for c in (0..3).rev() {
        let s: f64 = (c + 1..3).map(|k| a[c][k] * v[k]).sum();
        v[c] = (b[c] - s) / a[c][c];
    }
    Some(v)
}

/// Algebraic (Kåsa) circle fit: minimises Σ (x² + y² + D x + E y + F)², on coordinates
/// centred at the points' mean.
fn fit_kasa(pts: &[(f64, f64)]) -> Option<(f64, f64, f64)> {
    if pts.len() < 3 {
        return None;
    }
    let n = pts.len() as f64;
    let mx = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let my = pts.iter().map(|p| p.1).sum::<f64>() / n;
    let mut a = [[0.0; 3]; 3];
    let mut b = [0.0; 3];
    for &(x, y) in pts {
        let (u, v) = (x - mx, y - my);
        let z = u * u + v * v;
        let row = [u, v, 1.0];
        for i in 0..3 {
            for j in 0..3 {
                a[i][j] += row[i] * row[j];
            }
            b[i] -= row[i] * z;
        }
    }
    let [d, e, f] = solve3(a, b)?;
    let (cx, cy) = (-d * 0.5, -e * 0.5);
    let r2 = cx * cx + cy * cy - f;
    (r2 > 0.0).then(|| (cx + mx, cy + my, r2.sqrt()))
}

/// Gauss–Newton iterations of the geometric fit, minimising Σ (|p − c| − r)².
fn fit_geometric(pts: &[(f64, f64)], mut c: (f64, f64, f64)) -> Option<(f64, f64, f64)> {
    if pts.len() < 3 {
        return None;
    }
    for _ in 0..6 {
        let mut a = [[0.0; 3]; 3];
        let mut b = [0.0; 3];
        for &(x, y) in pts {
            let (vx, vy) = (x - c.0, y - c.1);
            let d = (vx * vx + vy * vy).sqrt();
            if d == 0.0 {
                continue;
            }
            let j = [-vx / d, -vy / d, -1.0];
            let e = d - c.2;
            for r in 0..3 {
                for k in 0..3 {
                    a[r][k] += j[r] * j[k];
                }
                b[r] -= j[r] * e;
            }
        }
        let step = solve3(a, b)?;
        c = (c.0 + step[0], c.1 + step[1], c.2 + step[2]);
        if step.iter().all(|s| s.abs() < 1e-6) {
            break;
        }
    }
    (c.2 > 0.0 && c.0.is_finite() && c.1.is_finite() && c.2.is_finite()).then_some(c)
}

/// The search range and thresholds of one run.
struct Search {
    rmin: f64,
    rmax: f64,
    threshold: u32,
    dp: f64,
}

/// Geometric fit of the circle among `pts` (one edge polarity) near radius `r0` around
/// `(cx, cy)`: the points within `band` of the median distance start a Kåsa then a
/// Gauss–Newton fit, refitted three times on the points within [`FIT_BAND`] of the current
/// circle. Returns the circle and its final number of points; `None` if under 6 points or
/// degenerate.
fn fit_group(pts: &[(f64, f64)], cx: f64, cy: f64, band: f64) -> Option<((f64, f64, f64), usize)> {
    if pts.len() < 6 {
        return None;
    }
    let dist = |&(x, y): &(f64, f64), c: (f64, f64)| ((x - c.0).powi(2) + (y - c.1).powi(2)).sqrt();
    let mut d: Vec<f64> = pts.iter().map(|p| dist(p, (cx, cy))).collect();
    let mid = d.len() / 2;
    let (_, &mut median, _) = d.select_nth_unstable_by(mid, f64::total_cmp);
    let start: Vec<(f64, f64)> = pts
        .iter()
        .copied()
        .filter(|p| (dist(p, (cx, cy)) - median).abs() <= band)
        .collect();
    if start.len() < 6 {
        return None;
    }
    let mut c = fit_kasa(&start).and_then(|k| fit_geometric(&start, k))?;
    let mut support = 0;
    for _ in 0..3 {
        let kept: Vec<(f64, f64)> = pts
            .iter()
            .copied()
            .filter(|p| (dist(p, (c.0, c.1)) - c.2).abs() <= FIT_BAND)
            .collect();
        if kept.len() < 6 {
            return None;
        }
        support = kept.len();
        c = fit_geometric(&kept, c)?;
    }
    Some((c, support))
}

/// Radius estimate and sub-pixel refinement of the circle around accumulator centre
/// `(cx, cy)`; `None` when no radius has more than `threshold` supporting edge pixels or the
/// fit fails.
fn circle_at(edges: &Edges, cx: f64, cy: f64, s: &Search) -> Option<(f64, f64, f64)> {
    // Histogram of supporting distances, 1-px bins, over [rmin − 1, rmax + 1].
    let bins = s.rmax.ceil() as usize + 3;
    let mut count = vec![0u32; bins];
    let mut sum = vec![0f64; bins];
    edges.radial(cx, cy, (s.rmin - 1.0).max(0.5), s.rmax + 1.0, |_, d, _| {
        let b = d as usize;
        if b < bins {
            count[b] += 1;
            sum[b] += d;
        }
    });
    // Best 3-bin window centred on bin b (radii [b − 1, b + 2)), by support per unit radius.
    let mut best: Option<(f64, usize)> = None;
    let first = (s.rmin.floor() as usize).max(1);
    let last = (s.rmax.floor() as usize).min(bins - 2);
    for b in first..=last {
        let c = count[b - 1] + count[b] + count[b + 1];
        if c <= s.threshold {
            continue;
        }
        let score = f64::from(c) / (b as f64 + 0.5);
        if best.is_none_or(|(bs, _)| score > bs) {
            best = Some((score, b));
        }
    }
    let (_, b) = best?;
    let n = count[b - 1] + count[b] + count[b + 1];
    let r0 = (sum[b - 1] + sum[b] + sum[b + 1]) / f64::from(n);

    // Sub-pixel edge points near the estimate (the centre may be off by dp/√2), split by
    // polarity; the other edge of a line drawn as a ring lies up to MAX_LINE_WIDTH away.
    let band = FIT_BAND + 0.75 * s.dp;
    let reach = band + MAX_LINE_WIDTH;
    let mut near: [Vec<(f64, f64)>; 2] = [Vec::new(), Vec::new()];
    edges.radial(
        cx,
        cy,
        (r0 - reach).max(0.5),
        r0 + reach,
        |p, _, outwards| {
            near[usize::from(outwards)].push(edges.subpixel(p));
        },
    );
    let fits = [
        fit_group(&near[0], cx, cy, band),
        fit_group(&near[1], cx, cy, band),
    ];
    let (c, support) = match fits {
        [None, None] => return None,
        [Some(f), None] | [None, Some(f)] => f,
        [Some(a), Some(b)] => {
            let (p, q) = if a.1 >= b.1 { (a, b) } else { (b, a) };
            let (pc, qc) = (p.0, q.0);
            let paired = 2 * q.1 >= p.1
                && (pc.0 - qc.0).hypot(pc.1 - qc.1) <= 1.0
                && (pc.2 - qc.2).abs() <= MAX_LINE_WIDTH;
            if paired {
                // Both edges of a line: its middle.
                let (wp, wq) = (p.1 as f64, q.1 as f64);
                let w = wp + wq;
                (
                    (
                        (pc.0 * wp + qc.0 * wq) / w,
                        (pc.1 * wp + qc.1 * wq) / w,
                        (pc.2 + qc.2) * 0.5,
                    ),
                    p.1 + q.1,
                )
            } else {
                p
            }
        }
    };
    (support > s.threshold as usize).then_some(c)
}

/// Circles in the gray image `gray` (`width × height`, row-major) by the Hough gradient method
/// with sub-pixel refinement (see the module docs), strongest accumulator peak first.
///
/// # Errors
///
/// When the accumulator would exceed 2^28 cells, or `gray` does not hold `width × height`
/// samples.
pub fn hough_circles(
    gray: &[u8],
    width: usize,
    height: usize,
    o: &CircleOptions,
) -> Result<Vec<Circle>, String> {
    if gray.len() != width * height {
        return Err(format!(
            "{} samples for a {width}×{height} image",
            gray.len()
        ));
    }
    if width == 0 || height == 0 {
        return Ok(Vec::new());
    }
    let cols = ((width - 1) as f64 / o.dp + 0.5).floor() as usize + 1;
    let rows = ((height - 1) as f64 / o.dp + 0.5).floor() as usize + 1;
    if (cols + 2).saturating_mul(rows + 2) > MAX_CELLS {
        return Err(format!(
            "the accumulator would have {cols} × {rows} cells; use a larger dp"
        ));
    }
    let blurred;
    let gray = if o.sigma > 0.0 {
        let image = Image::from_u8(width, height, Channels::Gray, gray.to_vec())
            .map_err(|e| e.to_string())?;
        blurred = gaussian_blur(&image, o.sigma, o.sigma, 0, 0, BorderMode::Reflect101, 0.0);
        blurred.as_u8().ok_or("blur changed the depth")?
    } else {
        gray
    };
    let edges = edges_of(gray, width, height, o.canny_high);

    let diagonal = ((width * width + height * height) as f64).sqrt().ceil();
    let search = Search {
        rmin: o.min_radius.max(MIN_SEARCH_RADIUS),
        rmax: if o.max_radius > 0.0 {
            o.max_radius.min(diagonal)
        } else {
            diagonal
        },
        threshold: o.votes_threshold,
        dp: o.dp,
    };
    if search.rmin > search.rmax {
        return Ok(Vec::new());
    }

    let idp = 1.0 / o.dp;
    let rays: Vec<Ray> = edges
        .points
        .iter()
        .map(|p| Ray {
            x0: ((f64::from(p.x) * idp + 1.5) * ONE).floor() as i64,
            y0: ((f64::from(p.y) * idp + 1.5) * ONE).floor() as i64,
            sx: (f64::from(p.ux) * idp * ONE).round() as i64,
            sy: (f64::from(p.uy) * idp * ONE).round() as i64,
        })
        .collect();
    let acc = vote(
        &rays,
        cols,
        rows,
        search.rmin.ceil() as i64,
        search.rmax.floor() as i64,
    );
    let stride = cols + 2;

    // Accumulator centres, strongest first, min_dist apart.
    let mut spacing = Spacing::new(o.min_dist);
    let mut centres = Vec::new();
    for (votes, k) in peaks(&acc, cols, rows, o.votes_threshold) {
        let x = (k % stride - 1) as f64 * o.dp;
        let y = (k / stride - 1) as f64 * o.dp;
        if spacing.free(x, y) {
            spacing.insert(x, y);
            centres.push((votes, x, y));
        }
    }
    drop(acc);

    let limit = if o.max_circles == 0 {
        usize::MAX
    } else {
        o.max_circles
    };
    let mut kept = Spacing::new(o.min_dist);
    let mut circles = Vec::new();
    for batch in centres.chunks(CENTRE_BATCH) {
        let found: Vec<Option<(f64, f64, f64)>> = batch
            .par_iter()
            .map(|&(_, x, y)| circle_at(&edges, x, y, &search))
            .collect();
        for (&(votes, _, _), c) in batch.iter().zip(found) {
            let Some((x, y, radius)) = c else { continue };
            if radius < o.min_radius || radius > search.rmax || !kept.free(x, y) {
                continue;
            }
            kept.insert(x, y);
            circles.push(Circle {
                x,
                y,
                radius,
                votes,
            });
            if circles.len() >= limit {
                return Ok(circles);
            }
        }
    }
    Ok(circles)
}

/// Checks a finite number ≥ `min`.
fn check_at_least(name: &str, v: f64, min: f64) -> Result<(), String> {
    if v.is_finite() && v >= min {
        Ok(())
    } else {
        Err(format!("`{name}` must be a finite number ≥ {min}, got {v}"))
    }
}

params! {
    /// Parameters of `detect.hough_circles`.
    pub struct HoughCirclesParams {
        /// Inverse accumulator resolution: accumulator cells are dp × dp px (OpenCV's dp;
        /// ≥ 1, default 1). Larger values vote faster into a coarser grid; the final centres
        /// are refined to sub-pixel accuracy either way.
        dp: f64 = 1.0,
        /// Smallest distance between the centres of two reported circles, px (≥ 0; default
        /// 20). The stronger circle wins.
        min_dist_px: f64 = 20.0,
        /// Upper Canny threshold (Sobel 3×3 magnitude |dx| + |dy| of the blurred image; the
        /// lower threshold is half of it, as OpenCV's param1; default 100).
        canny_high: f64 = 100.0,
        /// A centre needs strictly more accumulator votes than this, and its radius strictly
        /// more supporting edge pixels (OpenCV's param2; default 30).
        votes_threshold: u32 = 30,
        /// Smallest radius, px (default 0; radii below 2 px are never searched).
        min_radius_px: f64 = 0.0,
        /// Largest radius, px (default 0 = up to the image diagonal).
        max_radius_px: f64 = 0.0,
        /// Largest number of circles, strongest first (0 = all; default 0).
        max_circles: u32 = 0,
        /// Standard deviation of the Gaussian pre-blur, px (0 = none; default 1). OpenCV's
        /// HoughCircles does not blur, but its users usually blur first; this does it here.
        sigma_px: f64 = 1.0,
    }
}

/// Hough circle detector (`detect.hough_circles`). See [`hough_circles`].
#[derive(Debug, Clone)]
pub struct HoughCircles {
    options: CircleOptions,
}

impl Op for HoughCircles {
    type Params = HoughCirclesParams;
    const ID: &'static str = "detect.hough_circles";
    const SUMMARY: &'static str =
        "Hough gradient circle detector with sub-pixel centres and radii (like HOUGH_GRADIENT).";
    const DOC: &'static str = r#"
Finds circles in an intensity image by the Hough gradient method, as OpenCV's
cv::HoughCircles(image, HOUGH_GRADIENT, dp, minDist, param1, param2, minRadius, maxRadius),
then refines each circle to sub-pixel accuracy.

Method:
1. The image is converted to gray u8 (u16: v/257; f32: clamp(v, 0, 1)·255; RGB(A): BT.601
   luma), then Gaussian blurred with sigma_px (0 = off; kernel round(6σ + 1) | 1, reflect-101).
2. Canny edges (3×3 Sobel, L1 magnitude, thresholds canny_high/2 and canny_high, as
   detect.canny) and the 3×3 Sobel gradient of the blurred image.
3. Every edge pixel votes along its gradient line, in both directions, once per px of radius
   for radii r in [max(min_radius_px, 2), max_radius_px], into an accumulator of dp × dp px
   cells (cell (i, j) holds centres nearest (i·dp, j·dp); rays stepped in 16-bit fixed point,
   stopping at the image edge).
4. Centre candidates: cells with more than votes_threshold votes that are greater than their
   left and upper neighbours and at least their right and lower ones (OpenCV's rule), strongest
   first; a candidate closer than min_dist_px to a stronger one is dropped.
5. Radius: the distances from the candidate to the edge pixels whose gradient lies within 26°
   of the line to it are binned per px; the 3-px window with the most support per unit radius
   among those with more than votes_threshold pixels gives the radius (none: no circle).
6. Refinement: the supporting edge pixels within 7.5 + 0.75·dp px of that radius are located
   to sub-pixel accuracy (the parabola through the gradient magnitudes across the edge,
   Devernay 1995) and split by polarity (gradient towards or away from the centre). Each group
   is fitted by the algebraic Kåsa circle on its pixels near their median distance, then by
   Gauss–Newton iterations of the geometric least-squares fit, three times re-selecting the
   pixels within 1.5 px of the fitted circle. The group with more pixels gives the circle;
   when the other has at least half as many, a centre within 1 px and a radius within 6 px,
   the two are the edges of a line drawn as a circle and the circle is their middle. A
   candidate whose fit fails or keeps no more than votes_threshold pixels is dropped, as are
   refined circles closer than min_dist_px to a stronger one or with radii outside
   [min_radius_px, max_radius_px].

Output: Matrix with one row per circle, columns x, y (centre, px, pixel centres at integer
coordinates), radius (px), votes (accumulator peak votes), sorted by votes, strongest first.

Differences from OpenCV: optional pre-blur; rays stepped with 16 instead of 10 fractional bits;
the radius histogram counts only edge pixels whose gradient points at the centre; sub-pixel
refinement and its support check (OpenCV reports accumulator-cell centres and histogram radii,
and off-centre secondary peaks of large circles as extra circles). A ring drawn as a line up to
6 px wide is found at the middle of its two edges. Concentric circles share one centre and only
the best-supported radius is reported, as in OpenCV.

References: H. K. Yuen, J. Princen, J. Illingworth, J. Kittler, "Comparative study of Hough
transform methods for circle finding", Image and Vision Computing 8(1), 1990; F. Devernay, "A
non-maxima suppression method for edge detection with sub-pixel accuracy", INRIA RR-2724,
1995; OpenCV cv::HoughCircles (HOUGH_GRADIENT).

Example:
    "circles": (op: "detect.hough_circles", inputs: { "image": "camera.image" },
                params: (min_dist_px: 40, votes_threshold: 40, min_radius_px: 10,
                         max_radius_px: 120)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Intensity image: gray, RGB or RGBA; u8, u16 or f32 (0–1).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "circles",
            PortType::Matrix,
            "One row per circle: x, y, radius (px), votes; strongest first.",
        )]
    }

    fn new(p: HoughCirclesParams) -> Result<Self, String> {
        check_at_least("dp", p.dp, 1.0)?;
        if p.dp > 64.0 {
            return Err(format!("`dp` must be ≤ 64, got {}", p.dp));
        }
        check_at_least("min_dist_px", p.min_dist_px, 0.0)?;
        check_at_least("canny_high", p.canny_high, 0.0)?;
        check_at_least("min_radius_px", p.min_radius_px, 0.0)?;
        check_at_least("max_radius_px", p.max_radius_px, 0.0)?;
        check_at_least("sigma_px", p.sigma_px, 0.0)?;
        if p.sigma_px > 100.0 {
            return Err(format!("`sigma_px` must be ≤ 100, got {}", p.sigma_px));
        }
        if p.max_radius_px > 0.0 && p.max_radius_px < p.min_radius_px {
            return Err(format!(
                "`max_radius_px` ({}) must be ≥ `min_radius_px` ({}) or 0",
                p.max_radius_px, p.min_radius_px
            ));
        }
        Ok(HoughCircles {
            options: CircleOptions {
                dp: p.dp,
                min_dist: p.min_dist_px,
                canny_high: p.canny_high,
                votes_threshold: p.votes_threshold,
                min_radius: p.min_radius_px,
                max_radius: p.max_radius_px,
                max_circles: p.max_circles as usize,
                sigma: p.sigma_px,
            },
        })
    }
}

impl Operator for HoughCircles {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let gray = gray_u8(image);
        let circles = hough_circles(&gray, image.width(), image.height(), &self.options)
            .map_err(OpError::failed)?;
        let data = circles
            .iter()
            .flat_map(|c| [c.x, c.y, c.radius, f64::from(c.votes)])
            .collect();
        let m = Matrix::new(circles.len(), 4, data).map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new().with("circles", Value::Matrix(m.into())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::params::Params;
    use proptest::prelude::*;

    /// A shape to render: centre, radius, and `None` for a filled disc or `Some(w)` for a ring
    /// of width w centred on the radius.
    type Shape = (f64, f64, f64, Option<f64>);

    /// Antialiased rendering (8×8 supersampling near the boundaries) of `shapes` in `fg` on
    /// `bg`, plus uniform noise in ±`noise` from a fixed seed.
    fn render(w: usize, h: usize, shapes: &[Shape], bg: f64, fg: f64, noise: f64) -> Vec<u8> {
        let mut state = 0x1234_5678_9abc_def0u64;
        let mut rnd = move || {
            state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        };
        let inside = |px: f64, py: f64, &(cx, cy, r, ring): &Shape| {
            let d = ((px - cx).powi(2) + (py - cy).powi(2)).sqrt();
            match ring {
                None => d < r,
                Some(wd) => (d - r).abs() < wd / 2.0,
            }
        };
        let mut img = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let (fx, fy) = (x as f64, y as f64);
                let mut cover = 0.0f64;
                for s in shapes {
                    let d = ((fx - s.0).powi(2) + (fy - s.1).powi(2)).sqrt();
                    let outer = s.2 + s.3.unwrap_or(0.0) / 2.0;
                    if d > outer + 1.0 {
                        continue;
                    }
                    let mut c = 0.0;
                    for sy in 0..8 {
                        for sx in 0..8 {
                            let px = fx - 0.5 + (sx as f64 + 0.5) / 8.0;
                            let py = fy - 0.5 + (sy as f64 + 0.5) / 8.0;
                            if inside(px, py, s) {
                                c += 1.0 / 64.0;
                            }
                        }
                    }
                    cover = cover.max(c);
                }
                let v = bg + (fg - bg) * cover + noise * (2.0 * rnd() - 1.0);
                img[y * w + x] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
        img
    }

    fn options() -> CircleOptions {
        CircleOptions {
            min_dist: 10.0,
            ..CircleOptions::default()
        }
    }

    /// The circle of `found` nearest to (x, y, r), asserting centre and radius within `tol`.
    fn assert_found(found: &[Circle], (x, y, r): (f64, f64, f64), tol: f64) -> Circle {
        let best = found
            .iter()
            .min_by(|a, b| {
                let da = (a.x - x).hypot(a.y - y) + (a.radius - r).abs();
                let db = (b.x - x).hypot(b.y - y) + (b.radius - r).abs();
                da.total_cmp(&db)
            })
            .unwrap_or_else(|| panic!("no circles, expected ({x}, {y}, {r})"));
        assert!(
            (best.x - x).hypot(best.y - y) <= tol && (best.radius - r).abs() <= tol,
            "expected ({x}, {y}, {r}) within {tol}, nearest {best:?} of {found:?}"
        );
        *best
    }

    #[test]
    fn antialiased_discs_subpixel() {
        let (w, h) = (160, 120);
        for (i, &(x, y, r)) in [
            (80.3, 60.7, 30.25),
            (71.77, 55.1, 12.6),
            (90.5, 58.5, 45.9),
            (40.0, 50.0, 8.0),
        ]
        .iter()
        .enumerate()
        {
            for (bg, fg) in [(40.0, 200.0), (220.0, 60.0)] {
                let noise = if i % 2 == 0 { 0.0 } else { 8.0 };
                let img = render(w, h, &[(x, y, r, None)], bg, fg, noise);
                let found = hough_circles(&img, w, h, &options()).unwrap();
                let c = assert_found(&found, (x, y, r), 0.5);
                assert_eq!(found[0], c, "the disc is the strongest: {found:?}");
                // Tighter in practice; the bound documents the accuracy.
                assert!(
                    (c.x - x).hypot(c.y - y) <= 0.2 && (c.radius - r).abs() <= 0.2,
                    "{c:?} vs ({x}, {y}, {r}) noise {noise}"
                );
            }
        }
    }

    #[test]
    fn rings_found_at_their_middle() {
        let (w, h) = (200, 160);
        let truth = [(60.4, 70.2, 35.3), (150.6, 90.9, 22.2)];
        for width in [1.0, 1.5, 2.0, 2.5, 3.0, 4.0] {
            let shapes: Vec<Shape> = truth
                .iter()
                .map(|&(x, y, r)| (x, y, r, Some(width)))
                .collect();
            let img = render(w, h, &shapes, 30.0, 230.0, 6.0);
            let found = hough_circles(&img, w, h, &options()).unwrap();
            eprintln!("width {width}: {found:?}");
            for t in truth {
                assert_found(&found, t, 0.5);
            }
            assert_eq!(found.len(), 2, "{found:?}");
        }
    }

    #[test]
    fn several_discs_with_noise_and_min_dist() {
        let (w, h) = (320, 240);
        let truth = [
            (60.2, 60.6, 35.4),
            (180.7, 70.3, 28.1),
            (260.5, 180.25, 40.75),
            (90.9, 180.1, 20.6),
            (170.3, 170.8, 15.3),
        ];
        let shapes: Vec<Shape> = truth.iter().map(|&(x, y, r)| (x, y, r, None)).collect();
        let img = render(w, h, &shapes, 50.0, 190.0, 10.0);
        let found = hough_circles(&img, w, h, &options()).unwrap();
        for t in truth {
            assert_found(&found, t, 0.5);
        }
        assert_eq!(found.len(), truth.len(), "{found:?}");
        assert!(found.windows(2).all(|p| p[0].votes >= p[1].votes));
        // max_circles keeps the strongest.
        let two = hough_circles(
            &img,
            w,
            h,
            &CircleOptions {
                max_circles: 2,
                ..options()
            },
        )
        .unwrap();
        assert_eq!(two[..], found[..2]);
        // A min_dist larger than the gap between two centres keeps only the stronger.
        let (a, b) = (truth[1], truth[4]);
        let gap = (a.0 - b.0).hypot(a.1 - b.1);
        let spaced = hough_circles(
            &img,
            w,
            h,
            &CircleOptions {
                min_dist: gap + 5.0,
                ..options()
            },
        )
        .unwrap();
        let near = |c: &Circle, t: (f64, f64, f64)| (c.x - t.0).hypot(c.y - t.1) < 1.0;
        let n = spaced.iter().filter(|c| near(c, a) || near(c, b)).count();
        assert_eq!(n, 1, "{spaced:?}");
        for (i, p) in spaced.iter().enumerate() {
            for q in &spaced[i + 1..] {
                assert!((p.x - q.x).hypot(p.y - q.y) >= gap + 5.0, "{spaced:?}");
            }
        }
    }

    #[test]
    fn radius_range_respected() {
        let (w, h) = (240, 160);
        let truth = [(60.0, 80.0, 15.2), (170.5, 80.5, 45.3)];
        let shapes: Vec<Shape> = truth.iter().map(|&(x, y, r)| (x, y, r, None)).collect();
        let img = render(w, h, &shapes, 30.0, 200.0, 4.0);
        let small = CircleOptions {
            min_radius: 5.0,
            max_radius: 25.0,
            ..options()
        };
        let found = hough_circles(&img, w, h, &small).unwrap();
        assert_found(&found, truth[0], 0.5);
        assert!(
            found.iter().all(|c| (5.0..=25.0).contains(&c.radius)),
            "{found:?}"
        );
        assert!(
            found
                .iter()
                .all(|c| (c.x - truth[1].0).hypot(c.y - truth[1].1) > 5.0)
        );
        let large = CircleOptions {
            min_radius: 30.0,
            max_radius: 60.0,
            ..options()
        };
        let found = hough_circles(&img, w, h, &large).unwrap();
        assert_found(&found, truth[1], 0.5);
        assert!(
            found.iter().all(|c| (30.0..=60.0).contains(&c.radius)),
            "{found:?}"
        );
        assert!(
            found
                .iter()
                .all(|c| (c.x - truth[0].0).hypot(c.y - truth[0].1) > 5.0)
        );
    }

    #[test]
    fn dp_two_still_subpixel() {
        let (w, h) = (200, 150);
        let truth = (101.3, 70.8, 40.4);
        let img = render(w, h, &[(truth.0, truth.1, truth.2, None)], 20.0, 180.0, 5.0);
        let o = CircleOptions {
            dp: 2.0,
            votes_threshold: 15,
            ..options()
        };
        let found = hough_circles(&img, w, h, &o).unwrap();
        assert_found(&found, truth, 0.3);
    }

    #[test]
    fn nothing_in_flat_or_tiny_images() {
        let o = options();
        assert!(hough_circles(&[], 0, 0, &o).unwrap().is_empty());
        assert!(hough_circles(&[], 0, 5, &o).unwrap().is_empty());
        assert!(hough_circles(&[7], 1, 1, &o).unwrap().is_empty());
        assert!(hough_circles(&[7, 200], 2, 1, &o).unwrap().is_empty());
        assert!(
            hough_circles(&vec![128; 64 * 48], 64, 48, &o)
                .unwrap()
                .is_empty()
        );
        // Noise alone (weak) gives nothing either.
        let img = render(96, 64, &[], 100.0, 100.0, 6.0);
        assert!(hough_circles(&img, 96, 64, &o).unwrap().is_empty());
        assert!(hough_circles(&[1, 2], 3, 3, &o).is_err());
    }

    #[test]
    fn deterministic_across_thread_counts() {
        let (w, h) = (300, 200);
        let shapes: Vec<Shape> = [
            (70.3, 90.1, 40.2),
            (200.6, 100.4, 55.5),
            (250.0, 30.0, 12.0),
        ]
        .iter()
        .map(|&(x, y, r)| (x, y, r, None))
        .collect();
        let img = render(w, h, &shapes, 60.0, 180.0, 12.0);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| hough_circles(&img, w, h, &options()).unwrap())
        };
        let one = run(1);
        assert!(one.len() >= 3);
        for threads in [2, 3, 8] {
            let other = run(threads);
            assert_eq!(one.len(), other.len());
            for (a, b) in one.iter().zip(&other) {
                assert_eq!(a.x.to_bits(), b.x.to_bits());
                assert_eq!(a.y.to_bits(), b.y.to_bits());
                assert_eq!(a.radius.to_bits(), b.radius.to_bits());
                assert_eq!(a.votes, b.votes);
            }
        }
    }

    /// The accumulator voted the straightforward way: every ray stepped from rmin until it
    /// leaves the accumulator or passes rmax.
    fn reference_vote(rays: &[Ray], cols: usize, rows: usize, rmin: i64, rmax: i64) -> Vec<u32> {
        let stride = cols + 2;
        let mut acc = vec![0u32; stride * (rows + 2)];
        for ray in rays {
            for sign in [1i64, -1] {
                let (sx, sy) = (ray.sx * sign, ray.sy * sign);
                let (mut x, mut y) = (ray.x0 + rmin * sx, ray.y0 + rmin * sy);
                for _ in rmin..=rmax {
                    let (i, j) = (x >> SHIFT, y >> SHIFT);
                    if i < 1 || j < 1 || i > cols as i64 || j > rows as i64 {
                        break;
                    }
                    acc[j as usize * stride + i as usize] += 1;
                    x += sx;
                    y += sy;
                }
            }
        }
        acc
    }

    proptest! {
        #[test]
        fn banded_vote_matches_reference(
            pts in prop::collection::vec((0i32..70, 0i32..90, -1.0f64..1.0, -1.0f64..1.0), 1..40),
            rmin in 0i64..6,
            span in 0i64..120,
            dp in prop::sample::select(vec![1.0f64, 1.5, 2.0, 3.0]),
        ) {
            let (w, h) = (70usize, 90usize);
            let cols = ((w - 1) as f64 / dp + 0.5).floor() as usize + 1;
            let rows = ((h - 1) as f64 / dp + 0.5).floor() as usize + 1;
            let rays: Vec<Ray> = pts
                .iter()
                .map(|&(x, y, gx, gy)| {
                    let m = gx.hypot(gy).max(1e-9);
                    Ray {
                        x0: ((f64::from(x) / dp + 1.5) * ONE).floor() as i64,
                        y0: ((f64::from(y) / dp + 1.5) * ONE).floor() as i64,
                        sx: (gx / m / dp * ONE).round() as i64,
                        sy: (gy / m / dp * ONE).round() as i64,
                    }
                })
                .collect();
            let got = vote(&rays, cols, rows, rmin, rmin + span);
            prop_assert_eq!(got, reference_vote(&rays, cols, rows, rmin, rmin + span));
        }

        #[test]
        fn ray_interval_is_exact(p in -5000i64..5000, s in -300i64..300, lo in -3000i64..3000,
                                 len in 0i64..3000) {
            let hi = lo + len;
            let (a, b) = ray_interval(p, s, lo, hi);
            for r in -100i64..100 {
                let inside = (lo..=hi).contains(&(p + r * s));
                prop_assert_eq!(inside, a <= r && r <= b, "r {}", r);
            }
        }
    }

    #[test]
    fn fits_recover_exact_and_noisy_circles() {
        let (cx, cy, r) = (12.3, -4.5, 7.7);
        // A 120° arc: Kåsa is exact without noise; the geometric fit keeps it.
        let arc: Vec<(f64, f64)> = (0..40)
            .map(|i| {
                let t = f64::from(i) * 2.1 / 40.0;
                (cx + r * t.cos(), cy + r * t.sin())
            })
            .collect();
        let k = fit_kasa(&arc).unwrap();
        assert!((k.0 - cx).abs() < 1e-9 && (k.1 - cy).abs() < 1e-9 && (k.2 - r).abs() < 1e-9);
        let g = fit_geometric(&arc, (cx + 0.5, cy - 0.3, r + 0.4)).unwrap();
        assert!((g.0 - cx).abs() < 1e-9 && (g.1 - cy).abs() < 1e-9 && (g.2 - r).abs() < 1e-9);
        // Collinear points have no circle.
        let line: Vec<(f64, f64)> = (0..10)
            .map(|i| (f64::from(i), 2.0 * f64::from(i)))
            .collect();
        assert!(fit_kasa(&line).is_none());
        assert!(fit_kasa(&arc[..2]).is_none());
    }

    #[test]
    fn subpixel_edge_of_a_vertical_step() {
        // A blurred vertical step with its 50% point at x = 10.3: Canny marks column 10, the
        // parabola moves it towards 10.3.
        let (w, h) = (24, 9);
        let mut img = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let t = (x as f64 - 10.3) / 1.2;
                img[y * w + x] = (50.0 + 150.0 / (1.0 + (-1.7 * t).exp())).round() as u8;
            }
        }
        let edges = edges_of(&img, w, h, 60.0);
        let row4: Vec<&EdgePoint> = edges.points.iter().filter(|p| p.y == 4).collect();
        assert_eq!(row4.len(), 1, "one edge pixel per row");
        let (x, _) = edges.subpixel(row4[0]);
        assert!((x - 10.3).abs() < 0.1, "{x}");
    }

    fn run_op(params: HoughCirclesParams, image: Image) -> Result<Matrix, OpError> {
        let op = HoughCircles::new(params).map_err(OpError::failed)?;
        let specs = HoughCircles::inputs();
        let values = [Some(Value::image(image))];
        let ctx = RunContext {
            node: "circles".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values))?;
        match out.take("circles") {
            Some(Value::Matrix(m)) => Ok((*m).clone()),
            other => panic!("unexpected output {other:?}"),
        }
    }

    #[test]
    fn operator_accepts_all_formats() {
        let (w, h) = (100, 80);
        let (x, y, r) = (50.4, 40.6, 20.3);
        let img = render(w, h, &[(x, y, r, None)], 30.0, 210.0, 0.0);
        let params = HoughCirclesParams {
            min_dist_px: 10.0,
            ..HoughCirclesParams::default()
        };
        let images = [
            Image::from_u8(w, h, Channels::Gray, img.clone()).unwrap(),
            Image::from_u16(
                w,
                h,
                Channels::Gray,
                img.iter().map(|&v| u16::from(v) * 257).collect(),
            )
            .unwrap(),
            Image::from_f32(
                w,
                h,
                Channels::Gray,
                img.iter().map(|&v| f32::from(v) / 255.0).collect(),
            )
            .unwrap(),
            Image::from_u8(
                w,
                h,
                Channels::Rgb,
                img.iter().flat_map(|&v| [v, v, v]).collect(),
            )
            .unwrap(),
        ];
        let mut first: Option<Matrix> = None;
        for image in images {
            let m = run_op(params.clone(), image).unwrap();
            assert_eq!(m.cols, 4);
            assert!(m.rows >= 1);
            let row = &m.data[..4];
            assert!(
                (row[0] - x).hypot(row[1] - y) < 0.3 && (row[2] - r).abs() < 0.3,
                "{row:?}"
            );
            match &first {
                None => first = Some(m),
                Some(f) => assert_eq!(f.data, m.data, "same gray samples, same circles"),
            }
        }
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        assert_eq!(run_op(params, empty).unwrap().rows, 0);
    }

    #[test]
    fn bad_params_rejected() {
        let ok = HoughCirclesParams::default();
        assert!(HoughCircles::new(ok.clone()).is_ok());
        for bad in [
            HoughCirclesParams {
                dp: 0.5,
                ..ok.clone()
            },
            HoughCirclesParams {
                dp: f64::NAN,
                ..ok.clone()
            },
            HoughCirclesParams {
                dp: 100.0,
                ..ok.clone()
            },
            HoughCirclesParams {
                min_dist_px: -1.0,
                ..ok.clone()
            },
            HoughCirclesParams {
                canny_high: f64::INFINITY,
                ..ok.clone()
            },
            HoughCirclesParams {
                min_radius_px: f64::NAN,
                ..ok.clone()
            },
            HoughCirclesParams {
                max_radius_px: -3.0,
                ..ok.clone()
            },
            HoughCirclesParams {
                min_radius_px: 30.0,
                max_radius_px: 20.0,
                ..ok.clone()
            },
            HoughCirclesParams {
                sigma_px: -1.0,
                ..ok.clone()
            },
            HoughCirclesParams {
                sigma_px: 1e9,
                ..ok.clone()
            },
        ] {
            assert!(HoughCircles::new(bad.clone()).is_err(), "{bad:?}");
        }
        // Round trip through the parameter map.
        let map = ok.to_map();
        assert_eq!(HoughCirclesParams::from_map(&map).unwrap(), ok);
    }
}
