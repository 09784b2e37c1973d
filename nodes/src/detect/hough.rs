//! `detect.hough_lines` and `detect.hough_segments`: the standard and the progressive
//! probabilistic Hough transforms for lines, with OpenCV's accumulator conventions.
//!
//! [`hough_lines`] votes every nonzero pixel into a `(θ, ρ)` accumulator (`ρ = x cos θ + y sin θ`,
//! rounded to the nearest bin, bins offset by `(numrho − 1)/2`), keeps 4-neighbourhood local
//! maxima above the threshold exactly as `cv::HoughLines` does, then optionally suppresses
//! weaker peaks near stronger ones and refines peaks to sub-bin accuracy.
//! [`hough_segments`] is Matas et al.'s progressive probabilistic transform, as
//! `cv::HoughLinesP`, with a seeded pixel order.
//!
//! Voting is sequential per pixel but each θ row of the accumulator is independent, so the
//! standard transform votes θ rows in parallel (fixed rows, integer counts: the result does not
//! depend on the thread count). The probabilistic transform is inherently sequential.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Matrix, PixelData, Value};
use rayon::prelude::*;

/// Largest accepted number of accumulator cells (θ bins × ρ bins).
const MAX_CELLS: usize = 1 << 28;

/// Nonzero pixel coordinates `(x, y)` of a gray image in raster order; errors for colour.
fn edge_points(image: &Image, op: &str) -> Result<Vec<(i32, i32)>, OpError> {
    if image.channels() != Channels::Gray {
        return Err(OpError::input(
            "image",
            format!(
                "{op} needs a gray edge image (nonzero = edge), got {}; run detect.canny first",
                image.format()
            ),
        ));
    }
    let w = image.width();
    let mut pts = Vec::new();
    let mut push = |i: usize| pts.push(((i % w) as i32, (i / w) as i32));
    match image.data() {
        PixelData::U8(v) => v
            .iter()
            .enumerate()
            .filter(|(_, s)| **s != 0)
            .for_each(|(i, _)| push(i)),
        PixelData::U16(v) => v
            .iter()
            .enumerate()
            .filter(|(_, s)| **s != 0)
            .for_each(|(i, _)| push(i)),
        PixelData::F32(v) => v
            .iter()
            .enumerate()
            .filter(|(_, s)| **s != 0.0)
            .for_each(|(i, _)| push(i)),
    }
    Ok(pts)
}

/// OpenCV's `cvRound` for the values seen here (round half to even, as `lrint`).
fn round(v: f32) -> i32 {
    v.round_ties_even() as i32
}

/// The accumulator geometry shared by both transforms.
struct Geometry {
    numangle: usize,
    numrho: usize,
    /// `cos θ_n / ρ_step`, `sin θ_n / ρ_step` in f32, as OpenCV's tables.
    cos: Vec<f32>,
    sin: Vec<f32>,
    rho: f64,
    theta: f64,
}

impl Geometry {
    fn new(width: usize, height: usize, rho: f64, theta: f64) -> Result<Geometry, String> {
        let numangle = ((std::f64::consts::PI / theta).round_ties_even() as usize).max(1);
        let numrho = ((((width + height) * 2 + 1) as f64 / rho).round_ties_even() as usize).max(1);
        if numangle.saturating_mul(numrho) > MAX_CELLS {
            return Err(format!(
                "the accumulator would have {numangle} × {numrho} cells; use coarser rho_px / \
                 theta_deg"
            ));
        }
        let irho = 1.0 / rho;
        let mut cos = Vec::with_capacity(numangle);
        let mut sin = Vec::with_capacity(numangle);
        let mut ang = 0.0f32;
        for _ in 0..numangle {
            cos.push((f64::from(ang).cos() * irho) as f32);
            sin.push((f64::from(ang).sin() * irho) as f32);
            ang += theta as f32;
        }
        Ok(Geometry {
            numangle,
            numrho,
            cos,
            sin,
            rho,
            theta,
        })
    }

    /// ρ bin of point (x, y) at angle bin n.
    fn bin(&self, n: usize, x: i32, y: i32) -> usize {
        let r = round(x as f32 * self.cos[n] + y as f32 * self.sin[n]);
        (r + (self.numrho as i32 - 1) / 2) as usize
    }
}

/// One detected line: `rho` (px), `theta` (rad), `votes`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HoughLine {
    /// Signed distance of the line from the origin (top-left pixel centre), px.
    pub rho: f64,
    /// Angle of the line's normal from the x axis, radians in [0, π).
    pub theta: f64,
    /// Accumulator votes of the peak.
    pub votes: u32,
}

/// Options of [`hough_lines`] beyond OpenCV's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LineOptions {
    /// ρ step, px.
    pub rho: f64,
    /// θ step, radians.
    pub theta: f64,
    /// Peaks need strictly more votes than this.
    pub threshold: u32,
    /// Largest number of lines (0: all).
    pub max_lines: usize,
    /// Suppress a peak within this ρ distance (px) of a stronger kept one (with `nms_theta`).
    pub nms_rho: f64,
    /// θ distance (radians) of the suppression window.
    pub nms_theta: f64,
    /// Refine each peak to the vote-weighted centroid of its 3×3 accumulator neighbourhood.
    pub refine: bool,
}

/// Standard Hough transform of the edge points `points` (`(x, y)` px) of a `width × height`
/// image, with `cv::HoughLines`' accumulator (θ_n = n·θ in f32 steps, n < round(π/θ);
/// ρ bins `round(x cos θ/ρ + y sin θ/ρ) + (numrho − 1)/2`, numrho = round((2(w + h) + 1)/ρ)),
/// peaks that are > threshold, > the left and lower neighbours and ≥ the right and upper ones,
/// sorted by votes (ties: lower θ bin, then lower ρ bin, first). Then, if enabled, peaks within
/// (nms_rho, nms_theta) of a stronger kept one are dropped (also across θ = 0 ≡ π with ρ
/// negated), and peaks are refined.
pub fn hough_lines(
    points: &[(i32, i32)],
    width: usize,
    height: usize,
    o: &LineOptions,
) -> Result<Vec<HoughLine>, String> {
    let g = Geometry::new(width, height, o.rho, o.theta)?;
    let stride = g.numrho + 2;
    // Accumulator with a zero frame: rows n + 1, columns r + 1.
    let mut acc = vec![0u32; (g.numangle + 2) * stride];
    acc[stride..(g.numangle + 1) * stride]
        .par_chunks_mut(stride)
        .enumerate()
        .for_each(|(n, row)| {
            for &(x, y) in points {
                row[g.bin(n, x, y) + 1] += 1;
            }
        });
    let mut peaks: Vec<(u32, usize)> = Vec::new();
    for n in 0..g.numangle {
        for r in 0..g.numrho {
            let base = (n + 1) * stride + r + 1;
            let v = acc[base];
            if v > o.threshold
                && v > acc[base - 1]
                && v >= acc[base + 1]
                && v > acc[base - stride]
                && v >= acc[base + stride]
            {
                peaks.push((v, base));
            }
        }
    }
    peaks.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
    let limit = if o.max_lines == 0 {
        usize::MAX
    } else {
        o.max_lines
    };
    let centre = (g.numrho as f64 - 1.0) * 0.5;
    let mut lines: Vec<HoughLine> = Vec::new();
    for &(votes, base) in &peaks {
        if lines.len() >= limit {
            break;
        }
        let n = base / stride - 1;
        let r = base % stride - 1;
        let (mut rb, mut nb) = (r as f64, n as f64);
        if o.refine {
            let (mut sw, mut sr, mut sn) = (0.0, 0.0, 0.0);
            for dn in 0..3 {
                for dr in 0..3 {
                    let w = f64::from(acc[base + dn * stride + dr - stride - 1]);
                    sw += w;
                    sr += w * (dr as f64 - 1.0);
                    sn += w * (dn as f64 - 1.0);
                }
            }
            if sw > 0.0 {
                rb += sr / sw;
                nb += sn / sw;
            }
        }
        let line = HoughLine {
            rho: (rb - centre) * g.rho,
            theta: nb * g.theta,
            votes,
        };
        let suppressed = (o.nms_rho > 0.0 || o.nms_theta > 0.0)
            && lines.iter().any(|k| {
                let pi = std::f64::consts::PI;
                let close =
                    |rho: f64, dt: f64| (rho - line.rho).abs() <= o.nms_rho && dt <= o.nms_theta;
                let dt = (k.theta - line.theta).abs();
                close(k.rho, dt) || close(-k.rho, (pi - dt).abs())
            });
        if !suppressed {
            lines.push(line);
        }
    }
    Ok(lines)
}

/// A small deterministic generator (SplitMix64) for the probabilistic transform's pixel order.
struct SplitMix(u64);

impl SplitMix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in 0..n (n > 0), by rejection-free multiply-shift (bias < 2^-32 for n < 2^32).
    fn below(&mut self, n: usize) -> usize {
        (((self.next() >> 32) * n as u64) >> 32) as usize
    }
}

/// Progressive probabilistic Hough transform (Matas, Galambos, Kittler 1998) as
/// `cv::HoughLinesP`: edge pixels are taken in a random order (from `seed`); each votes; when
/// its best θ bin reaches `threshold` votes, the line through it is followed in both directions
/// over gaps of at most `max_gap` px, its pixels are removed (and unvoted if the segment is at
/// least `min_length` px long in x or y) and the segment `(x1, y1, x2, y2)` is reported.
#[allow(clippy::too_many_arguments)]
pub fn hough_segments(
    points: &[(i32, i32)],
    width: usize,
    height: usize,
    rho: f64,
    theta: f64,
    threshold: u32,
    min_length: i32,
    max_gap: i32,
    max_lines: usize,
    seed: u64,
) -> Result<Vec<[i32; 4]>, String> {
    let g = Geometry::new(width, height, rho, theta)?;
    let (w, h) = (width as i32, height as i32);
    let mut acc = vec![0u32; g.numangle * g.numrho];
    let mut mask = vec![false; width * height];
    for &(x, y) in points {
        mask[y as usize * width + x as usize] = true;
    }
    let mut order: Vec<(i32, i32)> = points.to_vec();
    let mut rng = SplitMix(seed);
    let limit = if max_lines == 0 {
        usize::MAX
    } else {
        max_lines
    };
    let mut segments = Vec::new();
    const SHIFT: i32 = 16;
    let mut count = order.len();
    while count > 0 {
        let idx = rng.below(count);
        let (x, y) = order[idx];
        order[idx] = order[count - 1];
        count -= 1;
        if !mask[y as usize * width + x as usize] {
            continue;
        }
        let mut max_val = threshold.saturating_sub(1);
        let mut max_n = usize::MAX;
        for n in 0..g.numangle {
            let cell = &mut acc[n * g.numrho + g.bin(n, x, y)];
            *cell += 1;
            if max_val < *cell {
                max_val = *cell;
                max_n = n;
            }
        }
        if max_n == usize::MAX {
            continue;
        }
        // Direction along the line: (−sin θ, cos θ).
        let a = -f64::from(g.sin[max_n]);
        let b = f64::from(g.cos[max_n]);
        let (x0, y0, dx0, dy0, xflag);
        if a.abs() > b.abs() {
            xflag = true;
            dx0 = if a > 0.0 { 1 } else { -1 };
            dy0 = (b * f64::from(1 << SHIFT) / a.abs()).round_ties_even() as i32;
            x0 = x;
            y0 = (y << SHIFT) + (1 << (SHIFT - 1));
        } else {
            xflag = false;
            dy0 = if b > 0.0 { 1 } else { -1 };
            dx0 = (a * f64::from(1 << SHIFT) / b.abs()).round_ties_even() as i32;
            x0 = (x << SHIFT) + (1 << (SHIFT - 1));
            y0 = y;
        }
        let pixel = |px: i32, py: i32| {
            if xflag {
                (px, py >> SHIFT)
            } else {
                (px >> SHIFT, py)
            }
        };
        let mut ends = [(x, y); 2];
        for (k, end) in ends.iter_mut().enumerate() {
            let (dx, dy) = if k == 0 { (dx0, dy0) } else { (-dx0, -dy0) };
            let (mut px, mut py) = (x0, y0);
            let mut gap = 0;
            loop {
                let (j1, i1) = pixel(px, py);
                if j1 < 0 || j1 >= w || i1 < 0 || i1 >= h {
                    break;
                }
                if mask[i1 as usize * width + j1 as usize] {
                    gap = 0;
                    *end = (j1, i1);
                } else {
                    gap += 1;
                    if gap > max_gap {
                        break;
                    }
                }
                px += dx;
                py += dy;
            }
        }
        let good = (ends[1].0 - ends[0].0).abs() >= min_length
            || (ends[1].1 - ends[0].1).abs() >= min_length;
        for (k, &end) in ends.iter().enumerate() {
            let (dx, dy) = if k == 0 { (dx0, dy0) } else { (-dx0, -dy0) };
            let (mut px, mut py) = (x0, y0);
            loop {
                let (j1, i1) = pixel(px, py);
                if j1 < 0 || j1 >= w || i1 < 0 || i1 >= h {
                    break;
                }
                let m = &mut mask[i1 as usize * width + j1 as usize];
                if *m {
                    if good {
                        for n in 0..g.numangle {
                            let cell = &mut acc[n * g.numrho + g.bin(n, j1, i1)];
                            *cell = cell.saturating_sub(1);
                        }
                    }
                    *m = false;
                }
                if (j1, i1) == end {
                    break;
                }
                px += dx;
                py += dy;
            }
        }
        if good {
            segments.push([ends[0].0, ends[0].1, ends[1].0, ends[1].1]);
            if segments.len() >= limit {
                break;
            }
        }
    }
    Ok(segments)
}

/// Checks a positive finite step.
fn check_step(name: &str, v: f64) -> Result<(), String> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(format!("`{name}` must be a finite number > 0, got {v}"))
    }
}

params! {
    /// Parameters of `detect.hough_lines`.
    pub struct HoughLinesParams {
        /// Distance resolution of the accumulator, px (default 1).
        rho_px: f64 = 1.0,
        /// Angle resolution of the accumulator, degrees (default 1).
        theta_deg: f64 = 1.0,
        /// A peak needs strictly more votes (edge pixels) than this (default 100).
        threshold: u32 = 100,
        /// Largest number of lines returned, strongest first (0 = all; default 0).
        max_lines: u32 = 0,
        /// Peak suppression: drop a peak within nms_rho_px (px) and nms_theta_deg (degrees) of
        /// a stronger kept line (default 0 = off, OpenCV's behaviour).
        nms_rho_px: f64 = 0.0,
        /// Angular half-size of the suppression window, degrees (default 0 = off).
        nms_theta_deg: f64 = 0.0,
        /// Refine each peak to the vote-weighted centroid of its 3×3 accumulator
        /// neighbourhood (sub-bin ρ and θ; default false).
        refine: bool = false,
    }
}

/// Standard Hough line transform (`detect.hough_lines`). See [`hough_lines`].
#[derive(Debug, Clone)]
pub struct HoughLines {
    options: LineOptions,
}

impl Op for HoughLines {
    type Params = HoughLinesParams;
    const ID: &'static str = "detect.hough_lines";
    const SUMMARY: &'static str =
        "Standard Hough transform: straight lines (ρ, θ) through the pixels of an edge image.";
    const DOC: &'static str = r#"
Every nonzero pixel (x, y) of a gray edge image (any depth) votes, for every θ bin
θ_n = n·theta_deg (n < round(180/theta_deg)), in the ρ bin round(x cos θ_n/ρ + y sin θ_n/ρ)
shifted by (numrho − 1)/2, numrho = round((2(width + height) + 1)/rho_px). The origin is the
centre of the top-left pixel. Peaks are accumulator cells with more than `threshold` votes that
are > their left and lower neighbours and ≥ their right and upper ones; they are sorted by
votes (ties: smaller θ, then smaller ρ first). This is exactly cv::HoughLines (same tables in
f32, same rounding, same local-maximum rule), so results compare one to one.

Additions: peak suppression (a peak within nms_rho_px and nms_theta_deg of a stronger kept line
is dropped, also across θ = 0 ≡ 180° with ρ negated; 0 = off) and sub-bin refinement (each
peak moved to the vote-weighted centroid of its 3×3 neighbourhood; bins beyond θ = 0 and the
last θ count as empty).

Output: Matrix with one row per line, columns (rho_px, theta_rad, votes), strongest first.
Line points satisfy x cos θ + y sin θ = ρ.

Reference: R. Duda, P. Hart, "Use of the Hough transformation to detect lines and curves in
pictures", CACM 15(1), 1972; OpenCV cv::HoughLines.

Example:
    "lines": (op: "detect.hough_lines", inputs: { "image": "edges.edges" },
              params: (threshold: 80, nms_rho_px: 5, nms_theta_deg: 3)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Gray edge image, nonzero pixels are edges (e.g. detect.canny's output).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "lines",
            PortType::Matrix,
            "One row per line: rho_px, theta_rad, votes; strongest first.",
        )]
    }

    fn new(p: HoughLinesParams) -> Result<Self, String> {
        check_step("rho_px", p.rho_px)?;
        check_step("theta_deg", p.theta_deg)?;
        if p.theta_deg > 180.0 {
            return Err(format!("`theta_deg` must be ≤ 180, got {}", p.theta_deg));
        }
        for (name, v) in [
            ("nms_rho_px", p.nms_rho_px),
            ("nms_theta_deg", p.nms_theta_deg),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(format!("`{name}` must be a finite number ≥ 0, got {v}"));
            }
        }
        Ok(HoughLines {
            options: LineOptions {
                rho: p.rho_px,
                theta: p.theta_deg.to_radians(),
                threshold: p.threshold,
                max_lines: p.max_lines as usize,
                nms_rho: p.nms_rho_px,
                nms_theta: p.nms_theta_deg.to_radians(),
                refine: p.refine,
            },
        })
    }
}

impl Operator for HoughLines {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let points = edge_points(image, Self::ID)?;
        let lines = hough_lines(&points, image.width(), image.height(), &self.options)
            .map_err(OpError::failed)?;
        let data = lines
            .iter()
            .flat_map(|l| [l.rho, l.theta, f64::from(l.votes)])
            .collect();
        let m = Matrix::new(lines.len(), 3, data).map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new().with("lines", Value::Matrix(m.into())))
    }
}

params! {
    /// Parameters of `detect.hough_segments`.
    pub struct HoughSegmentsParams {
        /// Distance resolution of the accumulator, px (default 1).
        rho_px: f64 = 1.0,
        /// Angle resolution of the accumulator, degrees (default 1).
        theta_deg: f64 = 1.0,
        /// Votes a θ bin needs before its line is followed (default 50).
        threshold: u32 = 50,
        /// Shortest reported segment, px (its x or y extent; default 30).
        min_line_length: u32 = 30,
        /// Largest gap bridged while following a line, px (default 10).
        max_line_gap: u32 = 10,
        /// Largest number of segments (0 = all; default 0).
        max_lines: u32 = 0,
        /// Seed of the random pixel order (default 0); the same seed gives the same result.
        seed: u64 = 0,
    }
}

/// Probabilistic Hough segments (`detect.hough_segments`). See [`hough_segments`].
#[derive(Debug, Clone)]
pub struct HoughSegments {
    p: HoughSegmentsParams,
}

impl Op for HoughSegments {
    type Params = HoughSegmentsParams;
    const ID: &'static str = "detect.hough_segments";
    const SUMMARY: &'static str =
        "Progressive probabilistic Hough transform: line segments in an edge image.";
    const DOC: &'static str = r#"
Matas et al.'s progressive probabilistic Hough transform, as cv::HoughLinesP. Edge pixels
(nonzero) are visited in a random order drawn from `seed` (SplitMix64; OpenCV uses its own RNG,
so individual segments can differ from OpenCV's while describing the same lines). Each pixel
votes in the same (θ, ρ) accumulator as detect.hough_lines; once its best θ bin has at least
`threshold` votes, the line through the pixel at that angle is walked in both directions
(fixed-point DDA, 16 fractional bits) across gaps of at most max_line_gap px. The walked edge
pixels are removed; if the segment's x or y extent is at least min_line_length they are also
unvoted and the segment is reported.

Output: Matrix, one row per segment: x1, y1, x2, y2 (px, integer end pixels), in detection
order.

Reference: J. Matas, C. Galambos, J. Kittler, "Robust detection of lines using the progressive
probabilistic Hough transform", CVIU 78(1), 2000; OpenCV cv::HoughLinesP.

Example:
    "segments": (op: "detect.hough_segments", inputs: { "image": "edges.edges" },
                 params: (threshold: 40, min_line_length: 30, max_line_gap: 5, seed: 1)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Gray edge image, nonzero pixels are edges.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "segments",
            PortType::Matrix,
            "One row per segment: x1, y1, x2, y2.",
        )]
    }

    fn new(p: HoughSegmentsParams) -> Result<Self, String> {
        check_step("rho_px", p.rho_px)?;
        check_step("theta_deg", p.theta_deg)?;
        if p.theta_deg > 180.0 {
            return Err(format!("`theta_deg` must be ≤ 180, got {}", p.theta_deg));
        }
        if p.min_line_length > i32::MAX as u32 || p.max_line_gap > i32::MAX as u32 {
            return Err("`min_line_length` and `max_line_gap` are too large".into());
        }
        Ok(HoughSegments { p })
    }
}

impl Operator for HoughSegments {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let points = edge_points(image, Self::ID)?;
        let p = &self.p;
        let segs = hough_segments(
            &points,
            image.width(),
            image.height(),
            p.rho_px,
            p.theta_deg.to_radians(),
            p.threshold,
            p.min_line_length as i32,
            p.max_line_gap as i32,
            p.max_lines as usize,
            p.seed,
        )
        .map_err(OpError::failed)?;
        let data = segs.iter().flat_map(|s| s.map(f64::from)).collect();
        let m = Matrix::new(segs.len(), 4, data).map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new().with("segments", Value::Matrix(m.into())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Pixels within half a pixel of the line x cos θ + y sin θ = ρ.
    fn thin_line(w: usize, h: usize, rho: f64, theta: f64) -> Vec<(i32, i32)> {
        let mut pts = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let d = x as f64 * theta.cos() + y as f64 * theta.sin() - rho;
                if d.abs() < 0.5 {
                    pts.push((x as i32, y as i32));
                }
            }
        }
        pts
    }

    fn options(threshold: u32) -> LineOptions {
        LineOptions {
            rho: 1.0,
            theta: 1f64.to_radians(),
            threshold,
            max_lines: 0,
            nms_rho: 3.0,
            nms_theta: 3f64.to_radians(),
            refine: true,
        }
    }

    fn assert_found(lines: &[HoughLine], rho: f64, theta: f64) {
        let ok = lines
            .iter()
            .any(|l| (l.rho - rho).abs() <= 0.5 && (l.theta - theta).abs() <= 0.5f64.to_radians());
        assert!(ok, "line ({rho}, {}°) not in {lines:?}", theta.to_degrees());
    }

    #[test]
    fn thin_lines_found() {
        let (w, h) = (200, 160);
        let truth = [
            (60.0, 30f64.to_radians()),
            (120.3, 100f64.to_radians()),
            (40.0, 0.0),
        ];
        let mut pts = Vec::new();
        for &(r, t) in &truth {
            pts.extend(thin_line(w, h, r, t));
        }
        pts.sort_by_key(|&(x, y)| (y, x));
        pts.dedup();
        let lines = hough_lines(&pts, w, h, &options(60)).unwrap();
        for &(r, t) in &truth {
            assert_found(&lines, r, t);
        }
        assert_eq!(lines.len(), 3, "{lines:?}");
        assert!(lines.windows(2).all(|p| p[0].votes >= p[1].votes));
    }

    #[test]
    fn canny_edges_of_thick_antialiased_line() {
        let (w, h) = (240, 200);
        let (rho, theta) = (110.0, 55f64.to_radians());
        let half = 4.0;
        // Antialiased band |d| < half (8×8 supersampling), 40 on 200.
        let mut img = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let mut cover = 0.0;
                for sy in 0..8 {
                    for sx in 0..8 {
                        let px = x as f64 - 0.5 + (sx as f64 + 0.5) / 8.0;
                        let py = y as f64 - 0.5 + (sy as f64 + 0.5) / 8.0;
                        let d = px * theta.cos() + py * theta.sin() - rho;
                        if d.abs() < half {
                            cover += 1.0 / 64.0;
                        }
                    }
                }
                img[y * w + x] = (40.0 + 160.0 * cover) as u8;
            }
        }
        let edges = crate::detect::canny::canny(&img, w, h, 50.0, 150.0, 3, false);
        let image = Image::from_u8(w, h, Channels::Gray, edges).unwrap();
        let pts = edge_points(&image, "t").unwrap();
        let lines = hough_lines(&pts, w, h, &options(80)).unwrap();
        // The two sides of the band, each within a pixel of ρ ± half (Canny puts the edge on
        // one side of the step), and the centre of the pair within 0.5 px.
        let a = lines
            .iter()
            .find(|l| (l.rho - (rho - half)).abs() < 1.5)
            .unwrap();
        let b = lines
            .iter()
            .find(|l| (l.rho - (rho + half)).abs() < 1.5)
            .unwrap();
        for l in [a, b] {
            assert!((l.theta - theta).abs() <= 0.5f64.to_radians(), "{l:?}");
        }
        assert!(((a.rho + b.rho) / 2.0 - rho).abs() <= 0.5, "{a:?} {b:?}");
    }

    #[test]
    fn opencv_rules_without_extras() {
        // One vertical line x = 5 of 10 pixels in a 12×12 image: OpenCV's peak is θ = 0,
        // ρ = 5 with 10 votes.
        let pts: Vec<(i32, i32)> = (1..11).map(|y| (5, y)).collect();
        let o = LineOptions {
            nms_rho: 0.0,
            nms_theta: 0.0,
            refine: false,
            ..options(9)
        };
        let lines = hough_lines(&pts, 12, 12, &o).unwrap();
        assert_eq!(
            lines[0],
            HoughLine {
                rho: 5.0,
                theta: 0.0,
                votes: 10
            }
        );
        assert!(
            hough_lines(&pts, 12, 12, &LineOptions { threshold: 10, ..o })
                .unwrap()
                .is_empty()
        );
        assert!(hough_lines(&[], 0, 0, &o).unwrap().is_empty());
    }

    /// Pixels within 1 px of the segment (a 3-px wide stroke, as edge detectors give for
    /// slanted lines).
    fn segment_points(s: [f64; 4]) -> Vec<(i32, i32)> {
        let (dx, dy) = (s[2] - s[0], s[3] - s[1]);
        let len2 = dx * dx + dy * dy;
        let mut pts = Vec::new();
        for y in 0..200 {
            for x in 0..250 {
                let (px, py) = (f64::from(x) - s[0], f64::from(y) - s[1]);
                let t = ((px * dx + py * dy) / len2).clamp(0.0, 1.0);
                let d2 = (px - t * dx).powi(2) + (py - t * dy).powi(2);
                if d2 <= 1.0 {
                    pts.push((x, y));
                }
            }
        }
        pts
    }

    #[test]
    fn segments_found_with_endpoints_within_2_px() {
        let (w, h) = (200, 150);
        let truth = [
            [20.0, 30.0, 170.0, 40.0],
            [30.0, 140.0, 60.0, 50.0],
            [100.0, 100.0, 190.0, 100.0],
        ];
        let mut pts: Vec<(i32, i32)> = truth.iter().flat_map(|&s| segment_points(s)).collect();
        pts.sort_by_key(|&(x, y)| (y, x));
        pts.dedup();
        for seed in [0, 1, 7] {
            let segs =
                hough_segments(&pts, w, h, 1.0, 0.5f64.to_radians(), 30, 30, 10, 0, seed).unwrap();
            for t in &truth {
                let found = segs.iter().any(|s| {
                    let d = |a: (f64, f64), b: (i32, i32)| {
                        ((a.0 - f64::from(b.0)).powi(2) + (a.1 - f64::from(b.1)).powi(2)).sqrt()
                    };
                    let (p, q) = ((t[0], t[1]), (t[2], t[3]));
                    let (s0, s1) = ((s[0], s[1]), (s[2], s[3]));
                    (d(p, s0) <= 2.0 && d(q, s1) <= 2.0) || (d(p, s1) <= 2.0 && d(q, s0) <= 2.0)
                });
                assert!(found, "seed {seed}: {t:?} not in {segs:?}");
            }
            // Deterministic for a seed.
            let again =
                hough_segments(&pts, w, h, 1.0, 0.5f64.to_radians(), 30, 30, 10, 0, seed).unwrap();
            assert_eq!(segs, again);
        }
    }

    #[test]
    fn rejects_bad_input() {
        assert!(
            HoughLines::new(HoughLinesParams {
                rho_px: 0.0,
                ..HoughLinesParams::default()
            })
            .is_err()
        );
        assert!(
            HoughLines::new(HoughLinesParams {
                theta_deg: f64::NAN,
                ..HoughLinesParams::default()
            })
            .is_err()
        );
        assert!(
            HoughSegments::new(HoughSegmentsParams {
                rho_px: -1.0,
                ..HoughSegmentsParams::default()
            })
            .is_err()
        );
        let rgb = Image::from_u8(2, 2, Channels::Rgb, vec![0; 12]).unwrap();
        assert!(edge_points(&rgb, "x").is_err());
    }
}
