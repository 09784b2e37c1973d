//! `detect.fast`: the FAST-9 corner detector (16-pixel circle), compatible with OpenCV's
//! `FastFeatureDetector` (`TYPE_9_16`).
//!
//! [`fast9`] scans each row in vectors of [`LANES`] centres with saturated u8 arithmetic: the
//! four compass pixels reject most vectors (an arc of 9 contains two adjacent ones, both
//! brighter than `v + t` or both darker than `v − t`); the others get, per lane, the best arc's
//! smallest saturated difference, which decides the corner test and is its score. Under AVX2 the
//! same step runs in `fast_avx2` (intrinsics, registers only, one polarity at a time). Scores go
//! to a small per-band buffer and non-maximum suppression compares each corner with its 8
//! neighbours. Bands of [`BAND_ROWS`] rows run in
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
    // Circular sliding minima / maxima over 9 taps by doubling: 2, 4, 8, then 8 + 1.
    let mut ext = [0i16; 32];
    ext[..16].copy_from_slice(d);
    ext[16..].copy_from_slice(d);
    let mut lo2 = [0i16; 24];
    let mut hi2 = [0i16; 24];
    for k in 0..24 {
        lo2[k] = ext[k].min(ext[k + 1]);
        hi2[k] = ext[k].max(ext[k + 1]);
    }
    let mut lo4 = [0i16; 20];
    let mut hi4 = [0i16; 20];
    for k in 0..20 {
        lo4[k] = lo2[k].min(lo2[k + 2]);
        hi4[k] = hi2[k].max(hi2[k + 2]);
    }
    let mut best = threshold;
    for k in 0..16 {
        let lo = lo4[k].min(lo4[k + 4]).min(ext[k + 8]);
        let hi = hi4[k].max(hi4[k + 4]).max(ext[k + 8]);
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

/// Lanes per screening vector.
const LANES: usize = 32;

/// One vector of lanes.
type Lanes = [u8; LANES];

/// `LANES` bytes of `s` from `at` (the caller keeps `at + LANES ≤ s.len()`).
#[inline(always)]
fn load(s: &[u8], at: usize) -> Lanes {
    let mut v = [0u8; LANES];
    v.copy_from_slice(&s[at..at + LANES]);
    v
}

/// Lane-wise `a − b`, saturating at 0.
#[inline(always)]
fn sub_sat(a: &Lanes, b: &Lanes) -> Lanes {
    let mut r = [0u8; LANES];
    for i in 0..LANES {
        r[i] = a[i].saturating_sub(b[i]);
    }
    r
}

/// Lane-wise minimum.
#[inline(always)]
fn min(a: &Lanes, b: &Lanes) -> Lanes {
    let mut r = [0u8; LANES];
    for i in 0..LANES {
        r[i] = a[i].min(b[i]);
    }
    r
}

/// Whether any lane is non-zero.
#[inline(always)]
fn any(a: &Lanes) -> bool {
    let mut acc = 0u8;
    for &v in a {
        acc |= v;
    }
    acc != 0
}

/// Per lane, the largest minimum of 9 circularly consecutive entries of `m` (clobbered):
/// minima of 2, then 4 in place, then windows of 9 as `k..k+4`, `k+4..k+8`, `k+5..k+9`.
#[inline(always)]
fn best_arc9(m: &mut [Lanes; 16]) -> Lanes {
    let m0 = m[0];
    for k in 0..15 {
        m[k] = min(&m[k], &m[k + 1]);
    }
    m[15] = min(&m[15], &m0);
    let (m0, m1) = (m[0], m[1]);
    for k in 0..14 {
        m[k] = min(&m[k], &m[k + 2]);
    }
    m[14] = min(&m[14], &m0);
    m[15] = min(&m[15], &m1);
    let mut best = [0u8; LANES];
    for k in 0..16 {
        let w = min(&min(&m[k], &m[(k + 4) % 16]), &m[(k + 5) % 16]);
        for i in 0..LANES {
            best[i] = best[i].max(w[i]);
        }
    }
    best
}

/// FAST test and score of the [`LANES`] centres from column `x`: writes `scores[x + i]` and
/// pushes `x + i` for the corners with `x + i ≥ from` (lanes below `from` were done before and
/// get the same score again).
///
/// With `B = max over arcs of 9 of min (p − v)⁺` and `D` the same for `(v − p)⁺`, the centre
/// is a corner exactly when `max(B, D) > t`, and its score (OpenCV's `cornerScore`, see
/// [`score`]) is then `max(B, D) − 1`: saturated u8 arithmetic, no comparisons.
#[inline(always)]
fn fast_vector(
    ring: &[&[u8]; 16],
    centre: &[u8],
    x: usize,
    from: usize,
    t: u8,
    scores: &mut [u8],
    corners: &mut Vec<usize>,
) {
    let v = load(centre, x);
    let mut hi = [0u8; LANES];
    let mut lo = [0u8; LANES];
    for i in 0..LANES {
        hi[i] = v[i].saturating_add(t);
        lo[i] = v[i].saturating_sub(t);
    }
    // Pixels 0, 4, 8, 12: an arc of 9 contains two adjacent ones, both > v + t or both
    // < v − t (non-zero saturated differences).
    let c = [
        load(ring[0], x),
        load(ring[4], x),
        load(ring[8], x),
        load(ring[12], x),
    ];
    let mut bright = [[0u8; LANES]; 4];
    let mut dark = [[0u8; LANES]; 4];
    for k in 0..4 {
        bright[k] = sub_sat(&c[k], &hi);
        dark[k] = sub_sat(&lo, &c[k]);
    }
    let mut pass = [0u8; LANES];
    for k in 0..4 {
        let b = min(&bright[k], &bright[(k + 1) % 4]);
        let d = min(&dark[k], &dark[(k + 1) % 4]);
        for i in 0..LANES {
            pass[i] |= b[i] | d[i];
        }
    }
    if !any(&pass) {
        return;
    }
    let mut m = [[0u8; LANES]; 16];
    for (k, mk) in m.iter_mut().enumerate() {
        *mk = sub_sat(&load(ring[k], x), &v);
    }
    let b = best_arc9(&mut m);
    for (k, mk) in m.iter_mut().enumerate() {
        *mk = sub_sat(&v, &load(ring[k], x));
    }
    let d = best_arc9(&mut m);
    let mut hit = [0u8; LANES];
    let mut score = [0u8; LANES];
    for i in 0..LANES {
        let s = b[i].max(d[i]);
        let corner = s > t;
        hit[i] = u8::from(corner);
        score[i] = if corner { s - 1 } else { 0 };
    }
    if any(&hit) {
        scores[x..x + LANES].copy_from_slice(&score);
        for (i, &h) in hit.iter().enumerate() {
            if h != 0 && x + i >= from {
                corners.push(x + i);
            }
        }
    }
}

/// FAST-9 corners of one row of at least [`LANES`] centres: `ring[k]` is the row of circle
/// pixel `k` (the slice starts at its offset from the first centre), `centre` the row of
/// centres, all `n` long or longer. Writes the scores of the corners into `scores` (which must
/// be zero at the others) and pushes their indices, ascending, into `corners`.
///
/// Vectors of [`LANES`] centres, the last one overlapping its predecessor; see
/// [`fast_vector`].
/// Where AVX2 is available, `fast_avx2::fast_row` runs instead (bit-identical, tested), so this
/// portable kernel is compiled for baseline x86-64 and SSE4.1 only.
#[multiversion::multiversion(targets("x86_64+sse4.1"))]
fn fast_row(
    ring: &[&[u8]; 16],
    centre: &[u8],
    n: usize,
    t: u8,
    scores: &mut [u8],
    corners: &mut Vec<usize>,
) {
    let mut x = 0;
    while x + LANES <= n {
        fast_vector(ring, centre, x, x, t, scores, corners);
        x += LANES;
    }
    if x < n && n >= LANES {
        fast_vector(ring, centre, n - LANES, x, t, scores, corners);
    }
}

/// Scores of row `y` for columns 3..width−3 into `scores` (width long; non-corners 0) and the
/// corner columns into `corners`. `scores` must be zero except at the columns `corners` held on
/// entry (they are cleared first). `found` is scratch.
fn score_row(
    img: &Region<'_>,
    y: usize,
    t: u8,
    scores: &mut [u8],
    found: &mut Vec<usize>,
    corners: &mut Vec<usize>,
) {
    for &x in corners.iter() {
        scores[x] = 0;
    }
    corners.clear();
    let n = img.width - 6;
    let at = |dy: isize, dx: isize| {
        let start = img.index(3, y) as isize + dy * img.stride as isize + dx;
        &img.data[start as usize..start as usize + n]
    };
    if n >= LANES {
        let ring: [&[u8]; 16] = CIRCLE.map(|(dx, dy)| at(dy, dx));
        found.clear();
        let row_scores = &mut scores[3..3 + n];
        #[cfg(target_arch = "x86_64")]
        let done = super::fast_avx2::fast_row(&ring, at(0, 0), n, t, row_scores, found);
        #[cfg(not(target_arch = "x86_64"))]
        let done = false;
        if !done {
            fast_row(&ring, at(0, 0), n, t, row_scores, found);
        }
        corners.extend(found.iter().map(|&i| i + 3));
        return;
    }
    // Narrow images: every pixel, scalar.
    let ti = i16::from(t);
    let offsets: [isize; 16] = CIRCLE.map(|(dx, dy)| dy * img.stride as isize + dx);
    for (x, s) in scores.iter_mut().enumerate().take(3 + n).skip(3) {
        let p = img.index(x, y);
        let v = i16::from(img.data[p]);
        let mut d = [0i16; 16];
        for (dk, &o) in d.iter_mut().zip(&offsets) {
            *dk = v - i16::from(img.data[(p as isize + o) as usize]);
        }
        if is_corner(&d, ti) {
            *s = score(&d, ti).clamp(0, 255) as u8;
            corners.push(x);
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
    if img.len() != width * height {
        return Vec::new();
    }
    fast9_region(img, width, (0, 0, width, height), t, nonmax)
}

/// A rectangle of a row-major image with `stride` bytes per row.
struct Region<'a> {
    data: &'a [u8],
    stride: usize,
    x0: usize,
    y0: usize,
    width: usize,
}

impl Region<'_> {
    /// Index in `data` of region pixel `(x, y)`.
    fn index(&self, x: usize, y: usize) -> usize {
        (self.y0 + y) * self.stride + self.x0 + x
    }
}

/// [`fast9`] of the rectangle `(x0, y0, width, height)` of an image with `stride` bytes per row,
/// as if it were cropped: corners at least 3 px inside the rectangle, scores outside it count as
/// 0 for the non-maximum suppression, coordinates relative to `(x0, y0)`. No copy is made.
/// Returns nothing when the rectangle does not lie inside `img`.
pub fn fast9_region(
    img: &[u8],
    stride: usize,
    (x0, y0, width, height): (usize, usize, usize, usize),
    t: u8,
    nonmax: bool,
) -> Vec<(usize, usize, u8)> {
    let inside = x0.checked_add(width).is_some_and(|right| right <= stride)
        && y0
            .checked_add(height)
            .and_then(|bottom| bottom.checked_mul(stride))
            .is_some_and(|end| end <= img.len());
    if width < 7 || height < 7 || !inside {
        return Vec::new();
    }
    let img = Region {
        data: img,
        stride,
        x0,
        y0,
        width,
    };
    let first = 3;
    let last = height - 3; // exclusive
    let bands = (last - first).div_ceil(BAND_ROWS);
    (0..bands)
        .into_par_iter()
        .map(|b| {
            let y0 = first + b * BAND_ROWS;
            let y1 = (y0 + BAND_ROWS).min(last);
            let mut found = Vec::new();
            let mut out = Vec::new();
            if !nonmax {
                let mut scores = vec![0u8; width];
                let mut corners = Vec::new();
                for y in y0..y1 {
                    score_row(&img, y, t, &mut scores, &mut found, &mut corners);
                    out.extend(corners.iter().map(|&x| (x, y, scores[x])));
                }
                return out;
            }
            // Ring of three score rows: y−1, y, y+1 (rows outside first..last are zero), with
            // the corner columns of each.
            let mut ring = [vec![0u8; width], vec![0u8; width], vec![0u8; width]];
            let mut cols: [Vec<usize>; 3] = [Vec::new(), Vec::new(), Vec::new()];
            for (slot, y) in [(0, y0 - 1), (1, y0)] {
                if y >= first {
                    score_row(&img, y, t, &mut ring[slot], &mut found, &mut cols[slot]);
                }
            }
            for y in y0..y1 {
                if y + 1 < last {
                    score_row(&img, y + 1, t, &mut ring[2], &mut found, &mut cols[2]);
                } else {
                    for &x in &cols[2] {
                        ring[2][x] = 0;
                    }
                    cols[2].clear();
                }
                let (prev, curr, next) = (&ring[0], &ring[1], &ring[2]);
                for &x in &cols[1] {
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
                cols.rotate_left(1);
            }
            out
        })
        .flatten()
        .collect()
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

Speed: rows are processed 32 centres at a time in saturated u8 arithmetic (vectorized, AVX2
when available): the four compass pixels reject most vectors (an arc of 9 always contains two
adjacent compass points); for the rest, the largest over 9-arcs of the smallest (p − v)⁺ or
(v − p)⁺ gives both the test (> t) and the score (minus 1), with no per-pixel branches.

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::random_u8;

    /// Direct reference: full test and score (largest t' with the point still a corner, by
    /// trying every t') at every pixel, then NMS against the 8 neighbours.
    fn reference(img: &[u8], w: usize, h: usize, t: u8, nonmax: bool) -> Vec<(usize, usize, u8)> {
        let corner_at = |x: usize, y: usize, t: i32| {
            let v = i32::from(img[y * w + x]);
            let ring: Vec<i32> = CIRCLE
                .iter()
                .map(|&(dx, dy)| {
                    i32::from(img[(y as isize + dy) as usize * w + (x as isize + dx) as usize])
                })
                .collect();
            (0..16).any(|k| {
                (0..9).all(|j| ring[(k + j) % 16] > v + t)
                    || (0..9).all(|j| ring[(k + j) % 16] < v - t)
            })
        };
        let mut score = vec![0i32; w * h];
        let mut is = vec![false; w * h];
        for y in 3..h.saturating_sub(3) {
            for x in 3..w.saturating_sub(3) {
                if corner_at(x, y, i32::from(t)) {
                    is[y * w + x] = true;
                    let mut s = i32::from(t);
                    while corner_at(x, y, s + 1) {
                        s += 1;
                    }
                    score[y * w + x] = s;
                }
            }
        }
        let mut out = Vec::new();
        for y in 3..h.saturating_sub(3) {
            for x in 3..w.saturating_sub(3) {
                if !is[y * w + x] {
                    continue;
                }
                let s = score[y * w + x];
                let keep = !nonmax
                    || [
                        (-1, -1),
                        (0, -1),
                        (1, -1),
                        (-1, 0),
                        (1, 0),
                        (-1, 1),
                        (0, 1),
                        (1, 1),
                    ]
                    .iter()
                    .all(|&(dx, dy)| {
                        s > score[(y as isize + dy) as usize * w + (x as isize + dx) as usize]
                    });
                if keep {
                    out.push((x, y, s as u8));
                }
            }
        }
        out
    }

    fn blocks(w: usize, h: usize, seed: u64) -> Vec<u8> {
        // Random 4×4 blocks: many corners of all scores.
        let noise = random_u8(w.div_ceil(4), h.div_ceil(4), Channels::Gray, seed);
        let n = noise.as_u8().unwrap();
        let bw = w.div_ceil(4);
        (0..w * h)
            .map(|i| n[(i / w / 4) * bw + (i % w) / 4])
            .collect()
    }

    #[test]
    fn matches_reference_on_random_images() {
        for (seed, t) in [(1u64, 20u8), (2, 5), (3, 60), (4, 0)] {
            let (w, h) = (77, 150);
            for img in [
                blocks(w, h, seed),
                random_u8(w, h, Channels::Gray, seed)
                    .as_u8()
                    .unwrap()
                    .to_vec(),
            ] {
                for nonmax in [false, true] {
                    assert_eq!(
                        fast9(&img, w, h, t, nonmax),
                        reference(&img, w, h, t, nonmax)
                    );
                }
            }
        }
    }

    /// The vector screening (whole vectors of 32 centres and the scalar tail) against the
    /// direct reference: widths around the vector length, saturating centres (0 and 255),
    /// thresholds 0 and 255, and images of a few levels where many pixels tie with v ± t.
    #[test]
    fn vector_path_matches_reference_on_edge_cases() {
        let mut cases: Vec<(usize, usize, Vec<u8>)> = Vec::new();
        for (i, w) in [7usize, 8, 37, 38, 39, 45, 70, 71, 72, 102, 133]
            .into_iter()
            .enumerate()
        {
            let h = 9 + i % 4;
            let seed = 100 + i as u64;
            cases.push((
                w,
                h,
                random_u8(w, h, Channels::Gray, seed)
                    .as_u8()
                    .unwrap()
                    .to_vec(),
            ));
            cases.push((w, h, blocks(w, h, seed)));
            // Few levels: 0, 20, 40, ..., 240 and 255, with exact ties at t = 20.
            let levels = random_u8(w, h, Channels::Gray, seed + 50);
            cases.push((
                w,
                h,
                levels
                    .as_u8()
                    .unwrap()
                    .iter()
                    .map(|&v| if v > 247 { 255 } else { (v / 20) * 20 })
                    .collect(),
            ));
            // Black and white only.
            cases.push((
                w,
                h,
                levels
                    .as_u8()
                    .unwrap()
                    .iter()
                    .map(|&v| if v & 1 == 0 { 0 } else { 255 })
                    .collect(),
            ));
        }
        for (w, h, img) in &cases {
            for t in [0u8, 1, 20, 40, 128, 254, 255] {
                for nonmax in [false, true] {
                    assert_eq!(
                        fast9(img, *w, *h, t, nonmax),
                        reference(img, *w, *h, t, nonmax),
                        "{w}×{h} t {t} nonmax {nonmax}"
                    );
                }
            }
        }
    }

    /// The AVX2 row kernel against the portable one, row by row: random, blocky and few-level
    /// images, row lengths around whole vectors (the overlapping tail), every threshold class.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_row_kernel_matches_the_portable_one() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        let mut checked = 0;
        for (i, w) in [38usize, 39, 45, 70, 71, 101, 134, 200]
            .into_iter()
            .enumerate()
        {
            let h = 12;
            let seed = 300 + i as u64;
            let random = random_u8(w, h, Channels::Gray, seed)
                .as_u8()
                .unwrap()
                .to_vec();
            let levels: Vec<u8> = random
                .iter()
                .map(|&v| if v > 247 { 255 } else { (v / 20) * 20 })
                .collect();
            for img in [random, blocks(w, h, seed), levels] {
                for t in [0u8, 1, 5, 20, 40, 128, 254, 255] {
                    for y in 3..h - 3 {
                        let n = w - 6;
                        let at = |dy: isize, dx: isize| {
                            let start = ((y as isize + dy) * w as isize + 3 + dx) as usize;
                            &img[start..start + n]
                        };
                        let ring: [&[u8]; 16] = CIRCLE.map(|(dx, dy)| at(dy, dx));
                        let (mut s1, mut c1) = (vec![0u8; n], Vec::new());
                        let (mut s2, mut c2) = (vec![0u8; n], Vec::new());
                        fast_row(&ring, at(0, 0), n, t, &mut s1, &mut c1);
                        assert!(super::super::fast_avx2::fast_row(
                            &ring,
                            at(0, 0),
                            n,
                            t,
                            &mut s2,
                            &mut c2
                        ));
                        assert_eq!((&s1, &c1), (&s2, &c2), "w {w} y {y} t {t}");
                        checked += c1.len();
                    }
                }
            }
        }
        assert!(checked > 1000, "too few corners compared: {checked}");
    }

    #[test]
    fn region_equals_a_crop() {
        let (w, h) = (120, 90);
        let img = blocks(w, h, 21);
        let (x0, y0, cw, ch) = (13, 7, 80, 70);
        let crop: Vec<u8> = img
            .chunks_exact(w)
            .skip(y0)
            .take(ch)
            .flat_map(|row| row[x0..x0 + cw].iter().copied())
            .collect();
        for nonmax in [false, true] {
            let expected = fast9(&crop, cw, ch, 10, nonmax);
            assert!(!expected.is_empty());
            assert_eq!(
                fast9_region(&img, w, (x0, y0, cw, ch), 10, nonmax),
                expected
            );
        }
        // Rectangles that do not fit give nothing.
        assert!(fast9_region(&img, w, (50, 0, 80, 10), 10, true).is_empty());
        assert!(fast9_region(&img, w, (0, 50, 10, 41), 10, true).is_empty());
    }

    #[test]
    fn single_bright_dot() {
        let (w, h) = (15, 15);
        let mut img = vec![10u8; w * h];
        img[7 * w + 7] = 200;
        // Score: the largest t' with 190 > t', i.e. 189.
        assert_eq!(fast9(&img, w, h, 20, true), vec![(7, 7, 189)]);
        assert_eq!(fast9(&img, w, h, 190, true), vec![]);
    }

    #[test]
    fn small_and_constant_images() {
        for (w, h) in [(0, 0), (1, 1), (6, 6), (7, 7), (7, 100)] {
            assert!(fast9(&vec![9u8; w * h], w, h, 10, true).is_empty());
        }
    }

    #[test]
    fn deterministic_across_threads() {
        let (w, h) = (200, 300);
        let img = blocks(w, h, 9);
        let many = fast9(&img, w, h, 10, true);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        assert_eq!(pool.install(|| fast9(&img, w, h, 10, true)), many);
    }

    #[test]
    fn rejects_non_gray_u8() {
        let op = Fast::new(FastParams::default()).unwrap();
        let specs = Fast::inputs();
        let ctx = RunContext {
            node: "fast".into(),
            threads: 1,
            element: None,
        };
        let rgb = ocellus_engine::value::Image::from_u8(8, 8, Channels::Rgb, vec![0; 192]).unwrap();
        let values = vec![Some(Value::image(rgb))];
        assert!(op.run(&ctx, &Inputs::new(&specs, &values)).is_err());
        assert!(
            Fast::new(FastParams {
                threshold: 256,
                ..FastParams::default()
            })
            .is_err()
        );
    }
}
