//! `describe.orb`: ORB, oriented FAST keypoints with rotated BRIEF descriptors (Rublee et al.,
//! ICCV 2011), with OpenCV's `cv::ORB` defaults and structure.
//!
//! [`orb_detect_and_compute`]:
//! 1. Converts the image to gray u8 and builds a pyramid of `n_levels` levels, level `l` scaled
//!    by `1 / scale_factor^(l − first_level)`: each level is the bilinear resize (OpenCV's
//!    `INTER_LINEAR` weights, [`resize`]) of the previous one to `round(W / s) × round(H / s)`
//!    (levels before `first_level` are enlarged from the input).
//! 2. Splits `max_features` over the levels geometrically (level `l` gets
//!    `round(N · (1 − 1/f) / (1 − 1/f^n) · f^−l)`, the last level the remainder), as OpenCV.
//! 3. On each level: FAST-9 with non-maximum suppression ([`fast9`]), drops corners closer than
//!    `max(edge_threshold, patch_size/2, 4)` px to the border, keeps the `2·budget` best by FAST
//!    score, scores them with Harris (7×7 block of 3×3 Sobel products, k = 0.04, OpenCV's
//!    scaling) and keeps the `budget` best (with the "harris" score; "fast" keeps the FAST score).
//!    Like OpenCV's `retainBest`, keypoints tied with the last one kept are kept too.
//! 4. Orientation: the intensity centroid over a disc of radius `patch_size/2` (pixels with
//!    `u² + v² ≤ (r + ½)²`), angle = atan2(m01, m10) in degrees, [0, 360).
//! 5. Smooths the level (Gaussian 7×7, σ = 2, reflect101) and computes the steered BRIEF bits
//!    of 256 tests (WTA_K 2) or 128 tuples (WTA_K 3 / 4, 2-bit codes), rotated by the
//!    keypoint angle with offsets rounded to the nearest pixel.
//!
//! Levels run in parallel (rayon) and are concatenated in level order; within a level keypoints
//! are sorted by decreasing response (ties in raster order), so the output is the same for any
//! thread count.
//!
//! The test pattern is not OpenCV's table: [`orb_pattern`] learns one, following the paper's
//! greedy decorrelation, on keypoints of a procedurally drawn training image (see its docs).

use std::borrow::Cow;
use std::sync::{Arc, Mutex, OnceLock};

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Descriptors, Image, Keypoint, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::brief::{SplitMix64, gaussian_point, smooth_gray};
use crate::detect::fast::fast9_region;
use crate::detect::gray::gray_u8;
use crate::filter::border::BorderMode;
use crate::filter::gaussian::gaussian_blur;
use crate::filter::resize::{Interpolation, Target, resize};

/// Harris constant of the keypoint ranking (OpenCV's `HARRIS_K`).
const HARRIS_K: f64 = 0.04;

/// Descriptor bytes (256 bits).
const BYTES: usize = 32;

/// Seed of the candidate tests and of the training image.
const ORB_SEED: u64 = 0x0DB0_1CC5_2011_0031;

param_enum! {
    /// How ORB ranks FAST corners.
    pub enum OrbScore {
        /// Harris corner measure at the FAST corner (OpenCV `ORB::HARRIS_SCORE`).
        Harris = "harris",
        /// The FAST score itself (OpenCV `ORB::FAST_SCORE`).
        Fast = "fast",
    }
}

#[allow(clippy::derivable_impls)]
impl Default for OrbScore {
    fn default() -> Self {
        OrbScore::Harris
    }
}

params! {
    /// Parameters of `describe.orb` (OpenCV `ORB::create` defaults).
    pub struct OrbParams {
        /// Largest number of keypoints kept (1..=1000000, default 500; OpenCV's `nfeatures`).
        max_features: u32 = 500,
        /// Pyramid decimation ratio between levels (> 1 and ≤ 4, default 1.2).
        scale_factor: f64 = 1.2,
        /// Number of pyramid levels (1..=32, default 8).
        n_levels: u32 = 8,
        /// Border in pixels, of each level, where no keypoint is detected (default 31); at least
        /// `patch_size/2` (and 4) is always used.
        edge_threshold: u32 = 31,
        /// Pyramid level holding the input image (default 0); earlier levels are enlarged
        /// copies. Must be below `n_levels`.
        first_level: u32 = 0,
        /// Points per descriptor test (2, 3 or 4, default 2): 2 gives 1 bit per test (the first
        /// point darker than the second), 3 and 4 give the 2-bit index of the brightest point.
        wta_k: u32 = 2,
        /// Keypoint ranking (default "harris").
        score: OrbScore = OrbScore::Harris,
        /// Side of the oriented patch, pixels (5..=255, default 31): orientation and tests lie
        /// within `patch_size/2` px of the keypoint (level pixels).
        patch_size: u32 = 31,
        /// FAST threshold, gray levels (0..=255, default 20).
        fast_threshold: u32 = 20,
    }
}

fn validate(p: &OrbParams) -> Result<(), String> {
    if !(1..=1_000_000).contains(&p.max_features) {
        return Err(format!(
            "`max_features` must be between 1 and 1000000, got {}",
            p.max_features
        ));
    }
    if !p.scale_factor.is_finite() || p.scale_factor <= 1.0 || p.scale_factor > 4.0 {
        return Err(format!(
            "`scale_factor` must be a finite number in (1, 4], got {}",
            p.scale_factor
        ));
    }
    if !(1..=32).contains(&p.n_levels) {
        return Err(format!(
            "`n_levels` must be between 1 and 32, got {}",
            p.n_levels
        ));
    }
    if p.first_level >= p.n_levels {
        return Err(format!(
            "`first_level` ({}) must be below `n_levels` ({})",
            p.first_level, p.n_levels
        ));
    }
    if !(2..=4).contains(&p.wta_k) {
        return Err(format!("`wta_k` must be 2, 3 or 4, got {}", p.wta_k));
    }
    if !(5..=255).contains(&p.patch_size) {
        return Err(format!(
            "`patch_size` must be between 5 and 255, got {}",
            p.patch_size
        ));
    }
    if p.fast_threshold > 255 {
        return Err(format!(
            "`fast_threshold` must be between 0 and 255, got {}",
            p.fast_threshold
        ));
    }
    if p.edge_threshold > 10_000 {
        return Err(format!(
            "`edge_threshold` must be at most 10000, got {}",
            p.edge_threshold
        ));
    }
    Ok(())
}

/// `umax[v]`: half-width of the orientation disc of radius `r` on row offset `v`
/// (`u² + v² ≤ (r + ½)²`, capped at r).
fn disc_half_widths(r: usize) -> Vec<i32> {
    let rr = (r as f64 + 0.5).powi(2);
    (0..=r)
        .map(|v| ((rr - (v * v) as f64).sqrt().floor() as i32).min(r as i32))
        .collect()
}

/// Harris measure at `(x, y)` (at least 4 px inside): 3×3 Sobel derivatives summed over a 7×7
/// block, `(det − k·trace²) · (1 / (4 · 7 · 255))⁴` as OpenCV's ORB `HarrisResponses`.
fn harris_at(img: &[u8], w: usize, x: usize, y: usize) -> f64 {
    let (mut a, mut b, mut c) = (0i64, 0i64, 0i64);
    for dy in 0..7 {
        let row = (y + dy - 3) * w + x - 3;
        for dx in 0..7 {
            let p = row + dx;
            let at = |q: usize| i64::from(img[q]);
            let ix = (at(p + 1) - at(p - 1)) * 2
                + (at(p - w + 1) - at(p - w - 1))
                + (at(p + w + 1) - at(p + w - 1));
            let iy = (at(p + w) - at(p - w)) * 2
                + (at(p + w - 1) - at(p - w - 1))
                + (at(p + w + 1) - at(p - w + 1));
            a += ix * ix;
            b += iy * iy;
            c += ix * iy;
        }
    }
    let scale = 1.0 / (4.0 * 7.0 * 255.0);
    let s4 = scale * scale * scale * scale;
    let (a, b, c) = (a as f64, b as f64, c as f64);
    (a * b - c * c - HARRIS_K * (a + b) * (a + b)) * s4
}

/// Intensity-centroid orientation at `(x, y)` over the disc `umax`, degrees in [0, 360).
///
/// Rows `±v` are summed together as slices (32-bit sums per row pair, which cannot overflow
/// for a patch of up to 255 px, then 64-bit totals), so the inner loop vectorizes.
fn ic_angle(img: &[u8], w: usize, x: usize, y: usize, umax: &[i32]) -> f32 {
    let centre = y * w + x;
    let r0 = umax[0] as usize;
    let mut m10 = 0i64;
    let mut m01 = 0i64;
    let middle = &img[centre - r0..=centre + r0];
    let mut row_m10 = 0i32;
    for (k, &p) in middle.iter().enumerate() {
        row_m10 += (k as i32 - r0 as i32) * i32::from(p);
    }
    m10 += i64::from(row_m10);
    for (v, &d) in umax.iter().enumerate().skip(1) {
        let d = d as usize;
        let top = &img[centre - v * w - d..=centre - v * w + d];
        let bottom = &img[centre + v * w - d..=centre + v * w + d];
        let mut row_m10 = 0i32;
        let mut sum_v = 0i32;
        for (k, (&t, &b)) in top.iter().zip(bottom).enumerate() {
            let (t, b) = (i32::from(t), i32::from(b));
            row_m10 += (k as i32 - d as i32) * (t + b);
            sum_v += b - t;
        }
        m10 += i64::from(row_m10);
        m01 += v as i64 * i64::from(sum_v);
    }
    let mut angle = (m01 as f64).atan2(m10 as f64).to_degrees();
    if angle < 0.0 {
        angle += 360.0;
    }
    let angle = angle as f32;
    if angle >= 360.0 { 0.0 } else { angle }
}

/// `x` rounded to the nearest integer, ties to even, for `|x| < 2²²`: the bits of
/// `x + 1.5·2²³` hold the rounded value in their low bits (the same value as
/// `round_small(x) as i32`, without a saturating float-to-integer conversion, so loops over it
/// vectorize).
#[inline(always)]
fn round_to_int(x: f32) -> i32 {
    const MAGIC: f32 = 12_582_912.0;
    (x + MAGIC).to_bits() as i32 - MAGIC.to_bits() as i32
}

/// Steered descriptor at `(x, y)` of the smoothed level: the pattern's points (groups of
/// `wta_k`) rotated by `angle_deg`, offsets rounded to the nearest pixel, ties to even (OpenCV's
/// convention: column `round(x cos − y sin)`, row `round(x sin + y cos)`). `offsets` is scratch.
#[allow(clippy::too_many_arguments)]
fn describe_at(
    img: &[u8],
    w: usize,
    x: usize,
    y: usize,
    angle_deg: f32,
    pattern: &[(i32, i32)],
    wta_k: usize,
    offsets: &mut Vec<isize>,
    out: &mut [u8],
) {
    let (sin, cos) = angle_deg.to_radians().sin_cos();
    let wi = w as isize;
    offsets.clear();
    offsets.resize(pattern.len(), 0);
    for (o, &(px, py)) in offsets.iter_mut().zip(pattern) {
        let (px, py) = (px as f32, py as f32);
        let col = round_to_int(px * cos - py * sin) as isize;
        let row = round_to_int(px * sin + py * cos) as isize;
        *o = row * wi + col;
    }
    let base = (y * w + x) as isize;
    let value = |o: isize| img[(base + o) as usize];
    if wta_k == 2 {
        for (byte, group) in out.iter_mut().zip(offsets.chunks_exact(16)) {
            let mut v = 0u8;
            for (j, pair) in group.chunks_exact(2).enumerate() {
                v |= u8::from(value(pair[0]) < value(pair[1])) << j;
            }
            *byte = v;
        }
    } else {
        for (byte, group) in out.iter_mut().zip(offsets.chunks_exact(4 * wta_k)) {
            let mut v = 0u8;
            for (j, tuple) in group.chunks_exact(wta_k).enumerate() {
                let mut best = 0u8;
                let mut best_value = value(tuple[0]);
                for (k, &o) in tuple.iter().enumerate().skip(1) {
                    let s = value(o);
                    if s > best_value {
                        best_value = s;
                        best = k as u8;
                    }
                }
                v |= best << (2 * j);
            }
            *byte = v;
        }
    }
}

/// Stable sort by decreasing response, then keep the first `n` and every later one tied with
/// the n-th (OpenCV's `retainBest`). The n-th response is found by selection first, so only
/// what is kept gets sorted.
fn retain_best<T>(items: &mut Vec<T>, n: usize, response: impl Fn(&T) -> f64) {
    if n == 0 {
        items.clear();
        return;
    }
    if items.len() > n {
        let mut responses: Vec<f64> = items.iter().map(&response).collect();
        let (_, &mut boundary, _) = responses.select_nth_unstable_by(n - 1, |a, b| b.total_cmp(a));
        items.retain(|t| response(t) >= boundary);
    }
    items.sort_by(|a, b| response(b).total_cmp(&response(a)));
}

/// Number of keypoints each of `levels` levels may keep.
fn level_budgets(n: usize, levels: usize, scale_factor: f64) -> Vec<usize> {
    let factor = 1.0 / scale_factor;
    let mut per = n as f64 * (1.0 - factor) / (1.0 - factor.powi(levels as i32));
    let mut out = Vec::with_capacity(levels);
    let mut sum = 0usize;
    for _ in 0..levels.saturating_sub(1) {
        let k = per.round_ties_even().max(0.0) as usize;
        out.push(k);
        sum += k;
        per *= factor;
    }
    out.push(n.saturating_sub(sum));
    out
}

/// Keypoints and descriptor bytes of one level.
type LevelOutput = (Vec<Keypoint>, Vec<u8>);

/// One level of the pyramid (the input level borrows a gray u8 input).
struct Level<'a> {
    image: Cow<'a, Image>,
    w: usize,
    h: usize,
    /// Level-0 pixels per level pixel, per axis (`W / w`, `H / h`).
    sx: f64,
    sy: f64,
    /// The nominal scale `scale_factor^(level − first_level)`.
    scale: f64,
}

fn gray_image(data: Vec<u8>, w: usize, h: usize) -> Result<Image, String> {
    Image::from_u8(w, h, Channels::Gray, data).map_err(|e| e.to_string())
}

/// The pyramid of gray u8 levels (stops early at an empty level).
fn pyramid<'a>(
    source: Cow<'a, Image>,
    w: usize,
    h: usize,
    p: &OrbParams,
) -> Result<Vec<Level<'a>>, String> {
    let first = p.first_level as usize;
    // The input level itself; moved into its level (levels before it are enlarged from it
    // first, later ones shrunk from their predecessor).
    let mut source = Some(source);
    let mut levels: Vec<Level<'a>> = Vec::with_capacity(p.n_levels as usize);
    for l in 0..p.n_levels as usize {
        let scale = p.scale_factor.powi(l as i32 - first as i32);
        let lw = (w as f64 / scale).round_ties_even() as usize;
        let lh = (h as f64 / scale).round_ties_even() as usize;
        if lw == 0 || lh == 0 {
            break;
        }
        let image = match (l.cmp(&first), levels.last(), source.as_ref()) {
            (std::cmp::Ordering::Equal, _, _) => source
                .take()
                .ok_or("internal: the input level was used twice")?,
            (std::cmp::Ordering::Greater, Some(prev), _) => Cow::Owned(resize(
                &prev.image,
                Target::Size(lw, lh),
                Interpolation::Bilinear,
            )?),
            (_, _, Some(src)) => {
                Cow::Owned(resize(src, Target::Size(lw, lh), Interpolation::Bilinear)?)
            }
            _ => return Err("internal: no source for a pyramid level".into()),
        };
        levels.push(Level {
            image,
            w: lw,
            h: lh,
            sx: w as f64 / lw as f64,
            sy: h as f64 / lh as f64,
            scale,
        });
    }
    Ok(levels)
}

/// FAST corners of `img` at least `border` px (≥ 4) from every side, found on the inner
/// rectangle (plus the 4-px ring FAST and its non-maximum suppression read), in raster order.
fn fast_inside(img: &[u8], w: usize, h: usize, t: u8, border: usize) -> Vec<(usize, usize, u8)> {
    let m = border - 4;
    let (cw, ch) = (w - 2 * m, h - 2 * m);
    fast9_region(img, w, (m, m, cw, ch), t, true)
        .into_iter()
        .map(|(x, y, s)| (x + m, y + m, s))
        .filter(|&(x, y, _)| x >= border && y >= border && x < w - border && y < h - border)
        .collect()
}

/// A keypoint candidate in level pixels.
#[derive(Clone, Copy)]
struct Candidate {
    x: usize,
    y: usize,
    response: f64,
}

/// Oriented keypoints of one level image, best first: `(x, y, response, angle)`.
fn level_keypoints(
    img: &[u8],
    w: usize,
    h: usize,
    budget: usize,
    p: &OrbParams,
) -> Vec<(usize, usize, f32, f32)> {
    let half = p.patch_size as usize / 2;
    let border = (p.edge_threshold as usize).max(half).max(4);
    if budget == 0 || w <= 2 * border || h <= 2 * border {
        return Vec::new();
    }
    let mut found: Vec<Candidate> = fast_inside(img, w, h, p.fast_threshold as u8, border)
        .into_iter()
        .map(|(x, y, s)| Candidate {
            x,
            y,
            response: f64::from(s),
        })
        .collect();
    match p.score {
        OrbScore::Harris => {
            retain_best(&mut found, 2 * budget, |c| c.response);
            for c in &mut found {
                c.response = harris_at(img, w, c.x, c.y);
            }
            retain_best(&mut found, budget, |c| c.response);
        }
        OrbScore::Fast => retain_best(&mut found, budget, |c| c.response),
    }
    let umax = disc_half_widths(half);
    found
        .iter()
        .map(|c| {
            (
                c.x,
                c.y,
                c.response as f32,
                ic_angle(img, w, c.x, c.y, &umax),
            )
        })
        .collect()
}

/// ORB keypoints (level-0 pixel coordinates, size `patch_size · scale`, angle in degrees,
/// octave = level) and their 32-byte binary descriptors. Any pixel format (converted to gray u8:
/// u16 as round(v/257), f32 as round(clamp(v,0,1)·255), colour as BT.601 luma). Images too small
/// for any keypoint give none.
pub fn orb_detect_and_compute(
    image: &Image,
    params: &OrbParams,
) -> Result<(Vec<Keypoint>, Descriptors), OpError> {
    validate(params).map_err(OpError::failed)?;
    let pattern = orb_pattern(params.patch_size as usize, params.wta_k as usize);
    orb_with_pattern(image, params, &pattern)
}

/// [`orb_detect_and_compute`] with a given test pattern (`pattern_points(wta_k)` points, each
/// inside the disc of radius `patch_size/2`), for experiments with patterns.
#[doc(hidden)]
pub fn orb_with_pattern(
    image: &Image,
    params: &OrbParams,
    pattern: &[(i32, i32)],
) -> Result<(Vec<Keypoint>, Descriptors), OpError> {
    validate(params).map_err(OpError::failed)?;
    let half = (params.patch_size / 2) as i32;
    if pattern.len() != pattern_points(params.wta_k as usize)
        || pattern.iter().any(|&(x, y)| x * x + y * y > half * half)
    {
        return Err(OpError::failed(
            "pattern: wrong size or points outside the patch",
        ));
    }
    let (w, h) = (image.width(), image.height());
    let empty = || {
        (
            Vec::new(),
            Descriptors::Binary {
                bytes: BYTES,
                data: Vec::new(),
            },
        )
    };
    if image.is_empty() {
        return Ok(empty());
    }
    // A gray u8 input is the input level itself; anything else is converted once.
    let source = match gray_u8(image) {
        Cow::Borrowed(_) => Cow::Borrowed(image),
        Cow::Owned(gray) => {
            Cow::Owned(gray_image(gray, w, h).map_err(|e| OpError::input("image", e))?)
        }
    };
    let levels = pyramid(source, w, h, params).map_err(|e| OpError::input("image", e))?;
    let budgets = level_budgets(
        params.max_features as usize,
        params.n_levels as usize,
        params.scale_factor,
    );
    let wta_k = params.wta_k as usize;
    let per_level: Vec<Result<LevelOutput, String>> = levels
        .par_iter()
        .zip(budgets.par_iter())
        .enumerate()
        .map(|(l, (level, &budget))| {
            let data = level
                .image
                .as_u8()
                .ok_or("internal: pyramid level is not u8")?;
            let found = level_keypoints(data, level.w, level.h, budget, params);
            if found.is_empty() {
                return Ok((Vec::new(), Vec::new()));
            }
            let blurred = gaussian_blur(&level.image, 2.0, 2.0, 7, 7, BorderMode::Reflect101, 0.0);
            let smooth = blurred
                .as_u8()
                .ok_or("internal: smoothing changed the sample type")?;
            let mut data = vec![0u8; found.len() * BYTES];
            let mut offsets = Vec::with_capacity(pattern.len());
            for (row, &(x, y, _, angle)) in data.chunks_exact_mut(BYTES).zip(&found) {
                describe_at(
                    smooth,
                    level.w,
                    x,
                    y,
                    angle,
                    pattern,
                    wta_k,
                    &mut offsets,
                    row,
                );
            }
            let keypoints = found
                .iter()
                .map(|&(x, y, response, angle)| Keypoint {
                    x: ((x as f64 + 0.5) * level.sx - 0.5) as f32,
                    y: ((y as f64 + 0.5) * level.sy - 0.5) as f32,
                    size: (params.patch_size as f64 * level.scale) as f32,
                    angle,
                    response,
                    octave: l as i32,
                })
                .collect();
            Ok((keypoints, data))
        })
        .collect();
    let (mut keypoints, mut data) = empty();
    let Descriptors::Binary { data: all, .. } = &mut data else {
        return Err(OpError::failed("internal: descriptor kind"));
    };
    for level in per_level {
        let (k, d) = level.map_err(|e| OpError::input("image", e))?;
        keypoints.extend(k);
        all.extend(d);
    }
    Ok((keypoints, data))
}

/// Number of pattern points for `wta_k`: 256 pairs, or 128 tuples (4 two-bit codes a byte).
fn pattern_points(wta_k: usize) -> usize {
    if wta_k == 2 {
        2 * 8 * BYTES
    } else {
        4 * BYTES * wta_k
    }
}

/// Learned patterns by patch size (WTA_K 2).
type PatternCache = Mutex<Vec<(usize, Arc<Vec<(i32, i32)>>)>>;

/// The ORB test pattern for `patch_size` and `wta_k`, as a flat list of points (pairs or
/// tuples of `wta_k`), every point inside the disc of radius `patch_size/2`.
///
/// For WTA_K 2 the 256 tests are learned, in the spirit of the paper's rBRIEF (section 4.3),
/// but entirely from generated data:
/// - 4096 candidate pairs are drawn (splitmix64, fixed seed) from an isotropic Gaussian of
///   σ = patch_size/5 around the centre, rounded to pixels, redrawn outside the disc or when both
///   points coincide;
/// - a 512×512 training image of 400 random discs and rotated rectangles (random grey levels,
///   then Gaussian σ = 1) gives up to 1500 ORB keypoints (FAST 20, Harris, intensity centroid);
///   every candidate is evaluated, steered, on each of them (after the 7×7 σ = 2 smoothing);
/// - candidates are ordered by how close their mean is to ½, then added greedily when their
///   absolute correlation with every test already chosen is at most a threshold, starting at
///   0.2 and raised by 0.05 until 256 tests are chosen.
///
/// The paper enumerates about 205 000 candidates. Drawing 4096 instead of 1024 raised the
/// correct-match ratio on 21 warped real image pairs from 0.859–0.882 to 0.876–0.894
/// (500–2000 features; BENCHMARKS.md, "ORB test pattern: 4096 candidates"). Learning, once per
/// process, takes about 65 ms instead of 30 ms (release build).
///
/// WTA_K 3 and 4 use Gaussian tuples of distinct points (no learning). Patterns are computed
/// once per patch size and cached.
pub fn orb_pattern(patch_size: usize, wta_k: usize) -> Arc<Vec<(i32, i32)>> {
    static CACHE: OnceLock<PatternCache> = OnceLock::new();
    let half = (patch_size / 2) as i32;
    if wta_k != 2 {
        let mut rng = SplitMix64::new(ORB_SEED ^ ((patch_size as u64) << 8) ^ wta_k as u64);
        let inside = move |x: i32, y: i32| x * x + y * y <= half * half;
        let sigma = patch_size as f64 / 5.0;
        let mut points = Vec::with_capacity(pattern_points(wta_k));
        while points.len() < pattern_points(wta_k) {
            let mut tuple: Vec<(i32, i32)> = Vec::with_capacity(wta_k);
            while tuple.len() < wta_k {
                let q = gaussian_point(&mut rng, 0.0, 0.0, sigma, inside);
                if !tuple.contains(&q) {
                    tuple.push(q);
                }
            }
            points.extend(tuple);
        }
        return Arc::new(points);
    }
    let cache = CACHE.get_or_init(|| Mutex::new(Vec::new()));
    if let Ok(guard) = cache.lock()
        && let Some((_, p)) = guard.iter().find(|(s, _)| *s == patch_size)
    {
        return p.clone();
    }
    let learned = Arc::new(learn_pattern(patch_size));
    if let Ok(mut guard) = cache.lock()
        && !guard.iter().any(|(s, _)| *s == patch_size)
    {
        guard.push((patch_size, learned.clone()));
    }
    learned
}

/// The deterministic training image of [`orb_pattern`].
#[cfg(test)]
fn training_image(side: usize, rng: &mut SplitMix64) -> Vec<u8> {
    training_image_model(side, rng, 400, 0, 0.0)
}

/// Power-law size between `lo` and `hi` (density ∝ r⁻³, the dead-leaves model's).
fn power_law_size(rng: &mut SplitMix64, lo: f64, hi: f64) -> f64 {
    let (a, b) = (lo.powi(-2), hi.powi(-2));
    (a - rng.uniform() * (a - b)).powf(-0.5)
}

/// Training image: `model` 0 draws sizes uniformly in 4..44 px; 1 draws them from a power law
/// in 2..120 px (dead leaves: scale-invariant statistics, like natural images). `noise` adds
/// Gaussian noise of that σ (gray levels) after the smoothing.
fn training_image_model(
    side: usize,
    rng: &mut SplitMix64,
    shapes: usize,
    model: u32,
    noise: f64,
) -> Vec<u8> {
    let mut img = vec![128u8; side * side];
    for _ in 0..shapes {
        let cx = rng.uniform() * side as f64;
        let cy = rng.uniform() * side as f64;
        let value = (rng.uniform() * 256.0) as u8;
        let disc = rng.uniform() < 0.4;
        let (a, b) = if model == 1 {
            let a = power_law_size(rng, 2.0, 120.0);
            (a, a * (0.3 + 0.7 * rng.uniform()))
        } else {
            (4.0 + rng.uniform() * 40.0, 4.0 + rng.uniform() * 40.0)
        };
        let (sin, cos) = (rng.uniform() * std::f64::consts::PI).sin_cos();
        let reach = a.max(b) * 1.5;
        let y0 = (cy - reach).max(0.0) as usize;
        let y1 = ((cy + reach) as usize).min(side - 1);
        let x0 = (cx - reach).max(0.0) as usize;
        let x1 = ((cx + reach) as usize).min(side - 1);
        for y in y0..=y1 {
            for x in x0..=x1 {
                let (dx, dy) = (x as f64 - cx, y as f64 - cy);
                let inside = if disc {
                    dx * dx + dy * dy <= a * a
                } else {
                    let u = dx * cos + dy * sin;
                    let v = -dx * sin + dy * cos;
                    u.abs() <= a && v.abs() <= b
                };
                if inside {
                    img[y * side + x] = value;
                }
            }
        }
    }
    let mut out = smooth_gray(&img, side, side, 1.0, 0).unwrap_or(img);
    if noise > 0.0 {
        for v in &mut out {
            *v = (f64::from(*v) + noise * rng.normal())
                .round()
                .clamp(0.0, 255.0) as u8;
        }
    }
    out
}

/// Settings of the pattern learning of [`orb_pattern`] (exposed for experiments; the operator
/// always uses [`PatternTraining::default`]).
#[doc(hidden)]
#[derive(Debug, Clone, PartialEq)]
pub struct PatternTraining {
    /// Candidate tests drawn.
    pub candidates: usize,
    /// Candidate points: Gaussian of σ = patch_size / `sigma_ratio`; 0 draws uniformly in the disc.
    pub sigma_ratio: f64,
    /// Training images (each of 512×512 px, a new random drawing).
    pub images: usize,
    /// Shapes drawn per training image.
    pub shapes: usize,
    /// Keypoints kept per training image.
    pub keypoints: usize,
    /// Starting correlation threshold of the greedy selection.
    pub threshold: f64,
    /// Seed offset (0: the operator's).
    pub seed: u64,
    /// Training image model (see `training_image_model`).
    pub model: u32,
    /// Noise σ added to training images, gray levels.
    pub noise: f64,
}

impl Default for PatternTraining {
    fn default() -> Self {
        PatternTraining {
            candidates: 4096,
            sigma_ratio: 5.0,
            images: 1,
            shapes: 400,
            keypoints: 1500,
            threshold: 0.2,
            seed: 0,
            model: 0,
            noise: 0.0,
        }
    }
}

fn learn_pattern(patch_size: usize) -> Vec<(i32, i32)> {
    learn_pattern_with(patch_size, &PatternTraining::default())
}

/// [`orb_pattern`]'s learning (WTA_K 2) under the settings `t`.
#[doc(hidden)]
pub fn learn_pattern_with(patch_size: usize, t: &PatternTraining) -> Vec<(i32, i32)> {
    const TESTS: usize = 8 * BYTES;
    const SIDE: usize = 512;
    let candidates_n = t.candidates.max(TESTS);
    let half = (patch_size / 2) as i32;
    let mut rng = SplitMix64::new(ORB_SEED ^ ((patch_size as u64) << 8) ^ t.seed);
    let inside = move |x: i32, y: i32| x * x + y * y <= half * half;
    let sigma = patch_size as f64 / t.sigma_ratio;
    let mut candidates: Vec<[(i32, i32); 2]> = Vec::with_capacity(candidates_n);
    let draw = |rng: &mut SplitMix64| {
        if t.sigma_ratio > 0.0 {
            gaussian_point(rng, 0.0, 0.0, sigma, inside)
        } else {
            loop {
                let x = rng.below(2 * half as usize + 1) as i32 - half;
                let y = rng.below(2 * half as usize + 1) as i32 - half;
                if inside(x, y) {
                    return (x, y);
                }
            }
        }
    };
    while candidates.len() < candidates_n {
        let a = draw(&mut rng);
        let b = draw(&mut rng);
        if a != b {
            candidates.push([a, b]);
        }
    }
    let params = OrbParams {
        patch_size: patch_size as u32,
        ..OrbParams::default()
    };
    // Per training keypoint: the bits of every candidate.
    let flat: Vec<(i32, i32)> = candidates.iter().flatten().copied().collect();
    let mut offsets = Vec::with_capacity(flat.len());
    let mut out = vec![0u8; candidates_n.div_ceil(8)];
    let mut samples: Vec<Vec<u8>> = Vec::new();
    for _ in 0..t.images.max(1) {
        let img = training_image_model(SIDE, &mut rng, t.shapes, t.model, t.noise);
        let found = level_keypoints(&img, SIDE, SIDE, t.keypoints, &params);
        let smooth = smooth_gray(&img, SIDE, SIDE, 2.0, 7).unwrap_or_else(|_| img.clone());
        for &(x, y, _, angle) in &found {
            describe_at(&smooth, SIDE, x, y, angle, &flat, 2, &mut offsets, &mut out);
            samples.push(out.clone());
        }
    }
    let n = samples.len();
    if n < 16 {
        // Too little training data (only for patches nearly as large as the image): keep the
        // Gaussian candidates as drawn.
        return candidates[..TESTS].iter().flatten().copied().collect();
    }
    // Bit vectors of every candidate over the training keypoints.
    let words = n.div_ceil(64);
    let mut bits = vec![0u64; candidates_n * words];
    for (k, out) in samples.iter().enumerate() {
        for c in 0..candidates_n {
            if out[c / 8] >> (c % 8) & 1 == 1 {
                bits[c * words + k / 64] |= 1 << (k % 64);
            }
        }
    }
    let row = |c: usize| &bits[c * words..(c + 1) * words];
    let mean: Vec<f64> = (0..candidates_n)
        .map(|c| row(c).iter().map(|w| w.count_ones()).sum::<u32>() as f64 / n as f64)
        .collect();
    let mut order: Vec<usize> = (0..candidates_n).collect();
    order.sort_by(|&a, &b| (mean[a] - 0.5).abs().total_cmp(&(mean[b] - 0.5).abs()));
    let corr = |a: usize, b: usize| -> f64 {
        let both = row(a)
            .iter()
            .zip(row(b))
            .map(|(x, y)| (x & y).count_ones())
            .sum::<u32>() as f64
            / n as f64;
        let den = (mean[a] * (1.0 - mean[a]) * mean[b] * (1.0 - mean[b])).sqrt();
        if den <= 0.0 {
            1.0
        } else {
            (both - mean[a] * mean[b]) / den
        }
    };
    let mut chosen: Vec<usize> = Vec::with_capacity(TESTS);
    let mut threshold = t.threshold;
    while chosen.len() < TESTS {
        for &c in &order {
            if chosen.len() == TESTS {
                break;
            }
            if chosen.contains(&c) {
                continue;
            }
            if chosen.iter().all(|&d| corr(c, d).abs() <= threshold) {
                chosen.push(c);
            }
        }
        threshold += 0.05;
    }
    chosen
        .iter()
        .flat_map(|&c| candidates[c].iter().copied())
        .collect()
}

/// ORB detector and descriptor (`describe.orb`). See [`orb_detect_and_compute`].
#[derive(Debug, Clone)]
pub struct Orb(OrbParams);

impl Op for Orb {
    type Params = OrbParams;
    const ID: &'static str = "describe.orb";
    const SUMMARY: &'static str =
        "ORB: oriented FAST keypoints on a pyramid with steered, learned BRIEF descriptors.";
    const DOC: &'static str = r#"
Oriented FAST and Rotated BRIEF, structured as OpenCV's `cv::ORB` (defaults equal
`cv2.ORB_create()`; `max_features` is `nfeatures`, `wta_k` is `WTA_K`):
1. Gray u8 pyramid of `n_levels` levels, each the bilinear resize (OpenCV `INTER_LINEAR`
   weights) of the previous level to round(W/s) × round(H/s), s = scale_factor^(l − first_level).
   OpenCV resizes padded levels with `INTER_LINEAR_EXACT`; values can differ by a gray level.
2. `max_features` split over the levels geometrically (OpenCV's formula, remainder to the last).
3. Per level: FAST-9 (threshold `fast_threshold`, non-maximum suppression), corners closer than
   max(edge_threshold, patch_size/2, 4) px to the border dropped, the 2·budget best by FAST
   score re-scored with Harris (7×7 block of 3×3 Sobel products, k = 0.04) and the budget best
   kept (OpenCV's `retainBest`: ties with the last kept are kept too). `score: "fast"` keeps the
   FAST score instead.
4. Orientation: intensity centroid over the disc u² + v² ≤ (patch_size/2 + ½)², exact atan2
   (OpenCV uses `fastAtan2`, ±0.3°), degrees in [0, 360).
5. Level smoothed with a 7×7 Gaussian, σ = 2 (reflect101), then 256 steered binary tests
   (rotated offsets rounded to the nearest pixel); bit j of byte i is test 8i + j. WTA_K 3/4:
   four 2-bit argmax codes per byte.

Keypoints: x, y in input-image pixels, mapped from level pixels as (x + ½)·W/w − ½ (OpenCV
multiplies by the nominal scale, which shifts coarse-level points by up to (s − 1)/2 px); size
= patch_size · s; angle in degrees; response = Harris (or FAST) score; octave = level. Levels
are concatenated in order, each sorted by decreasing response.

Test pattern: not OpenCV's learned table. 4096 Gaussian (σ = patch_size/5) candidate pairs
inside the patch disc are drawn from a fixed-seed generator and the 256 used are chosen by the
paper's greedy decorrelation (mean closest to ½ first, |correlation| ≤ 0.2, relaxed by 0.05
when short) on the steered tests of keypoints from a procedurally drawn training image.
Descriptors are therefore not interchangeable with OpenCV's. Keypoints equal OpenCV's on the
same gray image (level 0 exactly; coarser levels up to the resize rounding), so differences in
matching come from the pattern.

Input: any format (u16 as round(v/257), f32 as round(clamp(v, 0, 1)·255), colour as BT.601
luma). Images smaller than the border give no keypoints.

Reference: E. Rublee, V. Rabaud, K. Konolige, G. Bradski, "ORB: an efficient alternative to
SIFT or SURF", ICCV 2011; OpenCV features2d/src/orb.cpp.

Example:
    "orb": (op: "describe.orb", inputs: { "image": "load.image" }, params: (max_features: 1000)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to detect and describe (any format).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "keypoints",
                PortType::Keypoints,
                "Oriented keypoints, input-image pixels, level by level.",
            ),
            PortSpec::new(
                "descriptors",
                PortType::Descriptors,
                "32-byte binary descriptors, one row per keypoint.",
            ),
        ]
    }

    fn new(params: OrbParams) -> Result<Self, String> {
        validate(&params)?;
        Ok(Orb(params))
    }
}

impl Operator for Orb {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let (keypoints, descriptors) = orb_detect_and_compute(image, &self.0)?;
        Ok(Outputs::new()
            .with("keypoints", Value::Keypoints(keypoints.into()))
            .with("descriptors", Value::Descriptors(descriptors.into())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::resize::round_small;

    #[test]
    fn round_to_int_matches_round_small() {
        let mut x = -300.0f32;
        while x <= 300.0 {
            assert_eq!(round_to_int(x), round_small(x) as i32, "{x}");
            x += 0.125;
        }
        for x in [
            0.5f32, 1.5, 2.5, -0.5, -1.5, -2.5, 0.49999997, 180.5, -180.5,
        ] {
            assert_eq!(round_to_int(x), round_small(x) as i32, "{x}");
        }
    }
    use crate::filter::border::BorderMode;
    use crate::filter::warp::{Transform, WarpInterpolation, WarpOptions, warp};

    fn gray(w: usize, h: usize, f: impl Fn(usize, usize) -> u8) -> Image {
        let data = (0..w * h).map(|i| f(i % w, i / w)).collect();
        Image::from_u8(w, h, Channels::Gray, data).unwrap()
    }

    /// A textured test scene: the pattern-training drawing (discs and rotated rectangles).
    fn scene(side: usize, seed: u64) -> Image {
        let mut rng = SplitMix64::new(seed);
        Image::from_u8(side, side, Channels::Gray, training_image(side, &mut rng)).unwrap()
    }

    fn binary(d: &Descriptors) -> &[u8] {
        match d {
            Descriptors::Binary { bytes: 32, data } => data,
            _ => panic!("32-byte binary descriptors expected"),
        }
    }

    /// Brute-force Hamming nearest neighbours with a 0.8 ratio test: `(query, train)` pairs.
    fn matches(a: &[u8], b: &[u8]) -> Vec<(usize, usize)> {
        let dist = |x: &[u8], y: &[u8]| -> u32 {
            x.iter().zip(y).map(|(p, q)| (p ^ q).count_ones()).sum()
        };
        let mut out = Vec::new();
        for (i, da) in a.chunks_exact(32).enumerate() {
            let mut best = (u32::MAX, u32::MAX, 0usize);
            for (j, db) in b.chunks_exact(32).enumerate() {
                let d = dist(da, db);
                if d < best.0 {
                    best = (d, best.0, j);
                } else if d < best.1 {
                    best.1 = d;
                }
            }
            if (best.0 as f64) < 0.8 * best.1 as f64 {
                out.push((i, best.2));
            }
        }
        out
    }

    /// Fraction of ratio-test matches between `a` and `b` whose keypoints agree with `map`
    /// (a → b, input pixels) within `tol` px, and the number of matches.
    fn correct_ratio(
        a: &(Vec<Keypoint>, Descriptors),
        b: &(Vec<Keypoint>, Descriptors),
        map: impl Fn(f64, f64) -> (f64, f64),
        tol: f64,
    ) -> (f64, usize) {
        let m = matches(binary(&a.1), binary(&b.1));
        let good = m
            .iter()
            .filter(|&&(i, j)| {
                let (x, y) = map(f64::from(a.0[i].x), f64::from(a.0[i].y));
                (x - f64::from(b.0[j].x)).hypot(y - f64::from(b.0[j].y)) < tol
            })
            .count();
        (good as f64 / m.len().max(1) as f64, m.len())
    }

    #[test]
    fn budgets_follow_opencv() {
        assert_eq!(
            level_budgets(500, 8, 1.2),
            vec![109, 90, 75, 63, 52, 44, 36, 31]
        );
        for (n, l, f) in [(2000, 8, 1.2), (1, 3, 2.0), (7, 1, 1.5), (100, 32, 1.01)] {
            let b = level_budgets(n, l, f);
            assert_eq!((b.len(), b.iter().sum::<usize>()), (l, n));
        }
    }

    #[test]
    fn retain_best_keeps_ties() {
        let mut v = vec![3.0, 1.0, 5.0, 3.0, 3.0, 0.0];
        retain_best(&mut v, 2, |&x| x);
        assert_eq!(v, vec![5.0, 3.0, 3.0, 3.0]);
        let mut v = vec![1.0, 2.0];
        retain_best(&mut v, 0, |&x| x);
        assert!(v.is_empty());
    }

    #[test]
    fn harris_is_zero_on_flat_and_edges_negative_and_corners_positive() {
        let flat = vec![77u8; 81];
        assert_eq!(harris_at(&flat, 9, 4, 4), 0.0);
        // A vertical edge: only Ix ≠ 0, so det = 0 and the response is −k·trace² < 0.
        let edge = gray(9, 9, |x, _| if x < 4 { 0 } else { 200 });
        assert!(harris_at(edge.as_u8().unwrap(), 9, 4, 4) < 0.0);
        let corner = gray(9, 9, |x, y| if x < 4 && y < 4 { 200 } else { 0 });
        assert!(harris_at(corner.as_u8().unwrap(), 9, 4, 4) > 0.0);
        // Hand-computed: the 3×3 Sobel of a unit step of height 200 is 200·4 = 800 on the two
        // columns beside the step and 0 elsewhere: a = 7 rows · 2 · 800², b = c = 0 →
        // −0.04 · a² · (1/(4·7·255))⁴.
        let a = 7.0 * 2.0 * 800.0f64 * 800.0;
        let expected = -0.04 * a * a * (1.0 / (4.0 * 7.0 * 255.0f64)).powi(4);
        let got = harris_at(edge.as_u8().unwrap(), 9, 4, 4);
        assert!(
            (got - expected).abs() < 1e-12 * expected.abs(),
            "{got} vs {expected}"
        );
    }

    #[test]
    fn orientation_of_ramps_and_blobs() {
        let umax = disc_half_widths(15);
        assert_eq!(umax[0], 15);
        assert_eq!(umax[15], 3); // ⌊√(15.5² − 15²)⌋ = ⌊3.9⌋
        let c = 20;
        type Ramp = Box<dyn Fn(usize, usize) -> u8>;
        let cases: [(Ramp, f32); 4] = [
            (Box::new(|x, _| (x * 5) as u8), 0.0),  // brighter to the right
            (Box::new(|_, y| (y * 5) as u8), 90.0), // brighter downwards
            (Box::new(|x, _| (200 - x * 5) as u8), 180.0), // brighter to the left
            (Box::new(|x, y| (x * 2 + 100 - y * 2) as u8), 315.0), // right and up
        ];
        for (f, expected) in cases {
            let img = gray(41, 41, f);
            let a = ic_angle(img.as_u8().unwrap(), 41, c, c, &umax);
            let diff = (a - expected).rem_euclid(360.0);
            assert!(diff.min(360.0 - diff) < 0.01, "{a} vs {expected}");
        }
        // A bright blob to the lower left of the centre: angle ≈ 135°.
        let img = gray(41, 41, |x, y| {
            let (dx, dy) = (x as f32 - 14.0, y as f32 - 26.0);
            if dx * dx + dy * dy < 16.0 { 250 } else { 10 }
        });
        let a = ic_angle(img.as_u8().unwrap(), 41, c, c, &umax);
        assert!((a - 135.0).abs() < 1.0, "{a}");
    }

    #[test]
    fn hand_computed_steered_bits() {
        // I = 6x: unrotated, a test is 1 exactly when its first point is left of the second.
        // Rotated by 90°, offset (u, v) reads column −v, so a test is 1 when v1 > v2.
        let img = gray(40, 40, |x, _| (6 * x) as u8);
        let pattern = orb_pattern(31, 2);
        assert_eq!(pattern.len(), 512);
        for (angle, pick) in [(0.0f32, 0usize), (90.0, 1)] {
            let mut out = [0u8; 32];
            let mut offsets = Vec::new();
            describe_at(
                img.as_u8().unwrap(),
                40,
                20,
                20,
                angle,
                &pattern,
                2,
                &mut offsets,
                &mut out,
            );
            for (t, pair) in pattern.chunks_exact(2).enumerate() {
                let (a, b) = if pick == 0 {
                    (pair[0].0, pair[1].0)
                } else {
                    (-pair[0].1, -pair[1].1)
                };
                assert_eq!(
                    out[t / 8] >> (t % 8) & 1 == 1,
                    a < b,
                    "angle {angle} test {t}"
                );
            }
        }
    }

    #[test]
    fn patterns_are_inside_distinct_and_deterministic() {
        for (patch, k) in [(31usize, 2usize), (31, 3), (31, 4), (15, 2)] {
            let p = orb_pattern(patch, k);
            let r = (patch / 2) as i32;
            assert_eq!(p.len(), pattern_points(k));
            assert!(p.iter().all(|&(x, y)| x * x + y * y <= r * r));
            for group in p.chunks_exact(k) {
                for i in 0..k {
                    for j in i + 1..k {
                        assert_ne!(group[i], group[j]);
                    }
                }
            }
            assert_eq!(p, orb_pattern(patch, k));
        }
        // The learned pairs are spread out: no pair repeats.
        let p = orb_pattern(31, 2);
        let mut pairs: Vec<_> = p.chunks_exact(2).map(|c| (c[0], c[1])).collect();
        pairs.sort_unstable();
        pairs.dedup();
        assert_eq!(pairs.len(), 256);
    }

    #[test]
    fn keypoints_have_orb_fields() {
        let img = scene(320, 11);
        let p = OrbParams::default();
        let (k, d) = orb_detect_and_compute(&img, &p).unwrap();
        assert!(k.len() > 100 && k.len() <= 520, "{}", k.len());
        assert_eq!(d.len(), k.len());
        for kp in &k {
            assert!((0.0..360.0).contains(&kp.angle));
            assert!((0..8).contains(&kp.octave));
            let s = 1.2f32.powi(kp.octave);
            assert!((kp.size - 31.0 * s).abs() < 1e-3);
            assert!(kp.x >= 15.0 && kp.y >= 15.0 && kp.x < 305.0 && kp.y < 305.0);
        }
        // Octaves ascend; responses descend within an octave.
        for pair in k.windows(2) {
            assert!(pair[0].octave < pair[1].octave || pair[0].response >= pair[1].response);
        }
        assert!(k.iter().any(|kp| kp.octave > 2));
        // FAST score ranking and other WTA_K also run.
        for q in [
            OrbParams {
                score: OrbScore::Fast,
                ..p.clone()
            },
            OrbParams {
                wta_k: 4,
                ..p.clone()
            },
            OrbParams {
                first_level: 1,
                n_levels: 3,
                ..p.clone()
            },
        ] {
            let (k2, d2) = orb_detect_and_compute(&img, &q).unwrap();
            assert!(!k2.is_empty() && d2.len() == k2.len());
        }
    }

    /// Rotates `img` by `degrees` about its centre; returns the image and the forward map.
    fn rotated(img: &Image, degrees: f64) -> (Image, impl Fn(f64, f64) -> (f64, f64)) {
        let (s, c) = degrees.to_radians().sin_cos();
        let cx = (img.width() as f64 - 1.0) / 2.0;
        let cy = (img.height() as f64 - 1.0) / 2.0;
        // Destination → source: rotate by −degrees about the centre.
        let m = [c, s, cx - c * cx - s * cy, -s, c, cy + s * cx - c * cy];
        let options = WarpOptions {
            size: None,
            interpolation: WarpInterpolation::Bilinear,
            border: BorderMode::Reflect101,
            border_value: 0.0,
        };
        let out = warp(img, &Transform::Affine(m), &options).unwrap();
        let forward = move |x: f64, y: f64| {
            let (dx, dy) = (x - cx, y - cy);
            (cx + c * dx - s * dy, cy + s * dx + c * dy)
        };
        (out, forward)
    }

    #[test]
    fn rotation_invariance() {
        let img = scene(400, 21);
        let p = OrbParams::default();
        let base = orb_detect_and_compute(&img, &p).unwrap();
        for degrees in [0.0, 30.0, 90.0, 135.0, 200.0] {
            let (r, forward) = rotated(&img, degrees);
            let other = orb_detect_and_compute(&r, &p).unwrap();
            let (ratio, n) = correct_ratio(&base, &other, &forward, 3.0);
            assert!(
                ratio > 0.7 && n > 60,
                "{degrees}°: ratio {ratio}, {n} matches"
            );
        }
    }

    #[test]
    fn scale_invariance() {
        let img = scene(480, 31);
        let p = OrbParams::default();
        let base = orb_detect_and_compute(&img, &p).unwrap();
        for factor in [0.5, 0.7, 1.5, 2.0] {
            let scaled = resize(&img, Target::Scale(factor, factor), Interpolation::Area)
                .or_else(|_| resize(&img, Target::Scale(factor, factor), Interpolation::Bilinear))
                .unwrap();
            let other = orb_detect_and_compute(&scaled, &p).unwrap();
            let map = |x: f64, y: f64| ((x + 0.5) * factor - 0.5, (y + 0.5) * factor - 0.5);
            let (ratio, n) = correct_ratio(&base, &other, map, 3.0 * factor.max(1.0));
            assert!(
                ratio > 0.5 && n > 30,
                "×{factor}: ratio {ratio}, {n} matches"
            );
        }
    }

    #[test]
    fn extremes_and_formats() {
        let p = OrbParams::default();
        for (w, h) in [(0, 0), (1, 1), (8, 8), (62, 62), (5, 300)] {
            let img = gray(w, h, |x, y| ((x * 37 + y * 91) % 251) as u8);
            let (k, d) = orb_detect_and_compute(&img, &p).unwrap();
            assert!(k.is_empty() && d.is_empty(), "{w}×{h}");
        }
        let flat = gray(200, 200, |_, _| 90);
        assert!(orb_detect_and_compute(&flat, &p).unwrap().0.is_empty());
        // u16 (×257) and f32 (/255) give the u8 result.
        let img = scene(200, 41);
        let v = img.as_u8().unwrap();
        let w16 = Image::from_u16(
            200,
            200,
            Channels::Gray,
            v.iter().map(|&s| u16::from(s) * 257).collect(),
        )
        .unwrap();
        let wf = Image::from_f32(
            200,
            200,
            Channels::Gray,
            v.iter().map(|&s| f32::from(s) / 255.0).collect(),
        )
        .unwrap();
        let rgb = Image::from_u8(
            200,
            200,
            Channels::Rgb,
            v.iter().flat_map(|&s| [s, s, s]).collect(),
        )
        .unwrap();
        let a = orb_detect_and_compute(&img, &p).unwrap();
        assert!(!a.0.is_empty());
        for other in [w16, wf, rgb] {
            assert_eq!(orb_detect_and_compute(&other, &p).unwrap(), a);
        }
    }

    #[test]
    fn deterministic_across_threads_and_rejects_bad_params() {
        let img = scene(300, 51);
        let p = OrbParams {
            max_features: 800,
            ..OrbParams::default()
        };
        let many = orb_detect_and_compute(&img, &p).unwrap();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        assert_eq!(
            pool.install(|| orb_detect_and_compute(&img, &p)).unwrap(),
            many
        );
        let d = OrbParams::default();
        for bad in [
            OrbParams {
                max_features: 0,
                ..d.clone()
            },
            OrbParams {
                scale_factor: 1.0,
                ..d.clone()
            },
            OrbParams {
                scale_factor: f64::NAN,
                ..d.clone()
            },
            OrbParams {
                n_levels: 0,
                ..d.clone()
            },
            OrbParams {
                first_level: 8,
                ..d.clone()
            },
            OrbParams {
                wta_k: 5,
                ..d.clone()
            },
            OrbParams {
                patch_size: 3,
                ..d.clone()
            },
            OrbParams {
                fast_threshold: 256,
                ..d.clone()
            },
        ] {
            assert!(Orb::new(bad.clone()).is_err());
            assert!(orb_detect_and_compute(&img, &bad).is_err());
        }
    }
}
