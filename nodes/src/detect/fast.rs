//! `detect.fast`: the FAST-9 corner detector (16-pixel circle), compatible with OpenCV's
//! `FastFeatureDetector` (`TYPE_9_16`).
//!
//! [`fast9`] scans each row in two passes: a branch-free, vectorizable pass that keeps only
//! pixels where two adjacent compass points (of the four at distance 3) are both brighter than
//! `v + t` or both darker than `v − t` (necessary for any arc of 9), then the full arc test and
//! the score on those few candidates. Scores go to a small per-band buffer and non-maximum
//! suppression compares each corner with its 8 neighbours. Bands of [`BAND_ROWS`] rows run in
//! parallel and recompute the score rows just outside them, so the result does not depend on the
//! thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Keypoint, Value};
use rayon::prelude::*;

/// Rows per parallel band.
const BAND_ROWS: usize = 64;

/// Circle offsets (dx, dy), clockwise from the top, as OpenCV's pattern for 16 pixels.
const CIRCLE: [(isize, isize); 16] = [
    (0, -3),
    (1, -3),
    (2, -2),
    (3, -1),
    (3, 0),
    (3, 1),
    (2, 2),
    (1, 3),
    (0, 3),
    (-1, 3),
    (-2, 2),
    (-3, 1),
    (-3, 0),
    (-3, -1),
    (-2, -2),
    (-1, -3),
];

/// Score of a corner: the largest `t'` for which it is still a corner (strict comparisons), i.e.
/// `max over arcs of 9 of (min |v − p| over the arc, same sign)` − 1, floored at `t`... as
/// OpenCV's `cornerScore<16>`: `max(t, best arc) − 1`. `d[k] = v − p_k`.
fn score(d: &[i16; 16], threshold: i16) -> i16 {
    let mut best = threshold;
    for k in 0..16 {
        let mut lo = i16::MAX;
        let mut hi = i16::MIN;
        for j in 0..9 {
            let v = d[(k + j) & 15];
            lo = lo.min(v);
            hi = hi.max(v);
        }
        // Darker arc: all v − p ≥ lo; brighter arc: all p − v ≥ −hi.
        best = best.max(lo).max(-hi);
    }
    best - 1
}

/// True when 9 contiguous circle pixels are all `> v + t` or all `< v − t`.
fn is_corner(d: &[i16; 16], t: i16) -> bool {
    let mut bright = 0u32;
    let mut dark = 0u32;
    for (k, &v) in d.iter().enumerate() {
        // d = v − p: p brighter ⇔ d < −t.
        if v < -t {
            bright |= 1 << k;
        }
        if v > t {
            dark |= 1 << k;
        }
    }
    has_arc(bright) || has_arc(dark)
}

/// Whether the 16-bit circular mask has 9 consecutive set bits.
fn has_arc(mask: u32) -> bool {
    if mask.count_ones() < 9 {
        return false;
    }
    let doubled = mask | (mask << 16);
    let mut m = doubled;
    for _ in 1..9 {
        m &= m >> 1;
    }
    m & 0xFFFF != 0 || (m >> 16) & 0xFFFF != 0
}

/// Scores of row `y` (corners > 0, others 0) for columns 3..width−3, into `scores` (width
/// long). `flags` is scratch.
fn score_row(img: &[u8], width: usize, y: usize, t: u8, scores: &mut [u8], flags: &mut [u8]) {
    scores.fill(0);
    let n = width - 6;
    let at = |dy: isize, dx: isize| {
        let start = ((y as isize + dy) * width as isize + 3 + dx) as usize;
        &img[start..start + n]
    };
    let centre = at(0, 0);
    let top = at(-3, 0);
    let right = at(0, 3);
    let bottom = at(3, 0);
    let left = at(0, -3);
    // Pass 1: compass test, branch-free over the row.
    for (i, f) in flags[..n].iter_mut().enumerate() {
        let v = centre[i];
        let hi = v.saturating_add(t);
        let lo = v.saturating_sub(t);
        let (a, b, c, d) = (top[i], right[i], bottom[i], left[i]);
        let ba = (a > hi) as u8;
        let bb = (b > hi) as u8;
        let bc = (c > hi) as u8;
        let bd = (d > hi) as u8;
        let da = (a < lo) as u8;
        let db = (b < lo) as u8;
        let dc = (c < lo) as u8;
        let dd = (d < lo) as u8;
        *f = (ba & bb)
            | (bb & bc)
            | (bc & bd)
            | (bd & ba)
            | (da & db)
            | (db & dc)
            | (dc & dd)
            | (dd & da);
    }
    // Pass 2: full test on the candidates.
    let ti = i16::from(t);
    let offsets: [isize; 16] = CIRCLE.map(|(dx, dy)| dy * width as isize + dx);
    for (i, &f) in flags[..n].iter().enumerate() {
        if f == 0 {
            continue;
        }
        let x = i + 3;
        let p = y * width + x;
        let v = i16::from(img[p]);
        let mut d = [0i16; 16];
        for (dk, &o) in d.iter_mut().zip(&offsets) {
            *dk = v - i16::from(img[(p as isize + o) as usize]);
        }
        if is_corner(&d, ti) {
            scores[x] = score(&d, ti).clamp(0, 255) as u8;
        }
    }
}

/// FAST-9 corners of a gray 8-bit image (`width × height`, row-major): pixels at least 3 px
/// from the border with 9 contiguous pixels of the radius-3 circle all brighter than `v + t` or
/// all darker than `v − t`. With `nonmax`, a corner is kept only if its score (the largest
/// threshold at which it is still a corner, OpenCV's) is strictly greater than the scores of its
/// 8 neighbours (non-corners score 0). Returns `(x, y, score)` in raster order.
pub fn fast9(
    img: &[u8],
    width: usize,
    height: usize,
    t: u8,
    nonmax: bool,
) -> Vec<(usize, usize, u8)> {
    if width < 7 || height < 7 || img.len() != width * height {
        return Vec::new();
    }
    let first = 3;
    let last = height - 3; // exclusive
    let bands = (last - first).div_ceil(BAND_ROWS);
    (0..bands)
        .into_par_iter()
        .map(|b| {
            let y0 = first + b * BAND_ROWS;
            let y1 = (y0 + BAND_ROWS).min(last);
            let mut flags = vec![0u8; width];
            let mut out = Vec::new();
            if !nonmax {
                let mut scores = vec![0u8; width];
                for y in y0..y1 {
                    score_row(img, width, y, t, &mut scores, &mut flags);
                    for (x, &s) in scores.iter().enumerate() {
                        if s > 0 || is_corner_at(img, width, x, y, t, s) {
                            out.push((x, y, s));
                        }
                    }
                }
                return out;
            }
            // Ring of three score rows: y−1, y, y+1 (rows outside first..last are zero).
            let mut ring = [vec![0u8; width], vec![0u8; width], vec![0u8; width]];
            let mut corner_rows = [vec![false; width], vec![false; width], vec![false; width]];
            let mut fill = |row: &mut Vec<u8>, is: &mut Vec<bool>, y: usize| {
                if y >= first && y < last {
                    score_row(img, width, y, t, row, &mut flags);
                    mark_corners(img, width, y, t, row, is);
                } else {
                    row.fill(0);
                    is.fill(false);
                }
            };
            {
                let (r0, r1) = ring.split_at_mut(1);
                let (c0, c1) = corner_rows.split_at_mut(1);
                fill(&mut r0[0], &mut c0[0], y0 - 1);
                fill(&mut r1[0], &mut c1[0], y0);
            }
            for y in y0..y1 {
                {
                    let (r, c) = (&mut ring[2], &mut corner_rows[2]);
                    fill(r, c, y + 1);
                }
                let (prev, curr, next) = (&ring[0], &ring[1], &ring[2]);
                let is = &corner_rows[1];
                for x in 3..width - 3 {
                    if !is[x] {
                        continue;
                    }
                    let s = curr[x];
                    if s > curr[x - 1]
                        && s > curr[x + 1]
                        && s > prev[x - 1]
                        && s > prev[x]
                        && s > prev[x + 1]
                        && s > next[x - 1]
                        && s > next[x]
                        && s > next[x + 1]
                    {
                        out.push((x, y, s));
                    }
                }
                ring.rotate_left(1);
                corner_rows.rotate_left(1);
            }
            out
        })
        .flatten()
        .collect()
}

/// Marks the corners of row `y`: score > 0, or score 0 corners (possible only with `t` = 0).
fn mark_corners(img: &[u8], width: usize, y: usize, t: u8, scores: &[u8], is: &mut [bool]) {
    for (x, (c, &s)) in is.iter_mut().zip(scores).enumerate() {
        *c = s > 0 || is_corner_at(img, width, x, y, t, s);
    }
}

/// The full corner test at (x, y) for pixels scored 0 (only needed when `t` = 0, where a corner
/// can score 0). Pixels with a positive score are corners.
fn is_corner_at(img: &[u8], width: usize, x: usize, y: usize, t: u8, s: u8) -> bool {
    if s > 0 {
        return true;
    }
    if t > 0 || x < 3 || x + 3 >= width {
        return false;
    }
    let p = y * width + x;
    let v = i16::from(img[p]);
    let mut d = [0i16; 16];
    for (dk, &(dx, dy)) in d.iter_mut().zip(&CIRCLE) {
        let q = (p as isize + dy * width as isize + dx) as usize;
        *dk = v - i16::from(img[q]);
    }
    is_corner(&d, 0)
}

params! {
    /// Parameters of `detect.fast`.
    pub struct FastParams {
        /// Intensity threshold t (gray levels, 0..=255, default 20): circle pixels must be
        /// brighter than v + t or darker than v − t.
        threshold: u32 = 20,
        /// Keep only corners whose score beats all 8 neighbours (default true).
        nonmax_suppression: bool = true,
    }
}

/// FAST-9 detector (`detect.fast`). See [`fast9`].
#[derive(Debug, Clone)]
pub struct Fast {
    threshold: u8,
    nonmax: bool,
}

impl Op for Fast {
    type Params = FastParams;
    const ID: &'static str = "detect.fast";
    const SUMMARY: &'static str = "FAST-9 corner detector (16-pixel circle), OpenCV-compatible.";
    const DOC: &'static str = r#"
Features from Accelerated Segment Test: a pixel of value v (at least 3 px from the border) is a
corner when 9 contiguous pixels of the 16-pixel Bresenham circle of radius 3 are all > v + t or
all < v − t. Its score is the largest threshold at which it is still a corner (OpenCV's
`cornerScore<16>`: max over 9-arcs of the smallest |v − p| on the arc, minus 1). With
`nonmax_suppression`, a corner is kept only if its score is strictly greater than the scores of
its 8 neighbours (non-corners score 0).

Speed: each row is first screened branch-free with the four compass pixels (an arc of 9 always
contains two adjacent compass points), then candidates get the full test.

Keypoints come in raster order with size 7, angle −1, response = score, octave 0, matching
`cv::FastFeatureDetector::create(t, nonmax, TYPE_9_16)`. Gray u8 only.

References: E. Rosten, T. Drummond, "Machine learning for high-speed corner detection",
ECCV 2006; OpenCV features2d/src/fast.cpp.

Example:
    "fast": (op: "detect.fast", inputs: { "image": "gray.image" }, params: (threshold: 20)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("image", PortType::Image, "Gray u8 image.")]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "keypoints",
            PortType::Keypoints,
            "FAST corners, raster order.",
        )]
    }

    fn new(params: FastParams) -> Result<Self, String> {
        if params.threshold > 255 {
            return Err(format!(
                "`threshold` must be between 0 and 255, got {}",
                params.threshold
            ));
        }
        Ok(Fast {
            threshold: params.threshold as u8,
            nonmax: params.nonmax_suppression,
        })
    }
}

impl Operator for Fast {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let gray = match (image.channels(), image.as_u8()) {
            (Channels::Gray, Some(s)) => s,
            _ => {
                return Err(OpError::input(
                    "image",
                    format!(
                        "detect.fast needs a gray_u8 image, got {}; convert with \
                         filter.grayscale / filter.convert first",
                        image.format()
                    ),
                ));
            }
        };
        let found = fast9(
            gray,
            image.width(),
            image.height(),
            self.threshold,
            self.nonmax,
        );
        let keypoints: Vec<Keypoint> = found
            .into_iter()
            .map(|(x, y, s)| Keypoint {
                x: x as f32,
                y: y as f32,
                size: 7.0,
                angle: -1.0,
                response: f32::from(s),
                octave: 0,
            })
            .collect();
        Ok(Outputs::new().with("keypoints", Value::Keypoints(keypoints.into())))
    }
}
