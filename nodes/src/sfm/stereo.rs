//! `sfm.stereo`: the dense disparity map of a rectified stereo pair, by semi-global matching
//! (Hirschmüller 2008) or by block matching, with a left–right consistency check, a uniqueness
//! test, parabola subpixel refinement and a connected-component speckle filter.
//!
//! Convention: a left pixel `(x, y)` with disparity `d` shows the same point as the right pixel
//! `(x − d, y)`. Disparities `min_disparity + k`, `k = 0 … num_disparities − 1`, are searched;
//! at a pixel only those whose right pixel lies inside the image are candidates, so the left
//! border band still gets the disparities it can see.
//!
//! - **Census** ([`census`]): a `block_size × block_size` window, one bit per neighbour
//!   (`neighbour < centre`), matched by Hamming distance; borders replicate.
//! - **SGM** ([`sgm_step`]): the census cost `C(p, d)` (Hamming bits × [`COST_SCALE`], u8)
//!   is aggregated along 8 (or 4) straight paths `r`:
//!   `L_r(p, d) = C(p, d) + min(L_r(p−r, d), L_r(p−r, d±1) + P1, min_k L_r(p−r, k) + P2)
//!   − min_k L_r(p−r, k)` (Hirschmüller 2008, eq. 13), in u16: the subtraction keeps
//!   `L_r ≤ C_max + P2`, so the sum over paths `S(p, d)` fits u16 when
//!   `paths · (C_max + P2) < 2¹⁶` (checked). As in OpenCV's StereoSGBM, the paths run as two
//!   sweeps over the rows: downward (left to right, and the three paths from the row above)
//!   and upward (right to left, and the three from the row below); at each pixel the four
//!   steps of a sweep are one pass over the disparities in u16 vector lanes, and the costs
//!   come from the census words on the fly (popcounts of byte planes, u8 lanes), in each
//!   sweep, rather than stored. The one large buffer is `S`: `W · H · num_disparities · 2`
//!   bytes (Aloe 1282×1110, 224 disparities: 638 MB). The first sweep to reach a row writes
//!   its sum there, the second adds its own and decides the row. With two threads the sweeps
//!   run at the same time and meet in the middle; the sums are integer, so the result does
//!   not depend on the threads.
//! - **BM** ([`bm_costs_row`]): the sum of absolute differences, or `1 − ZNCC`, or the census
//!   Hamming distance over the `block_size` window, per row in parallel.
//! - **Decision** ([`decide_row`]): the winner `k` minimises `S`; it is rejected when another
//!   disparity more than 1 away has `S · (100 − uniqueness_ratio) < S_min · 100` (OpenCV's
//!   rule), refined from `S(k−1), S(k), S(k+1)` (the parabola through them for ZNCC, the
//!   equiangular fit for the V-shaped census and SAD curves), and checked against the
//!   right view's winner `k_R(x_r) = argmin_k S(x_r + d_k, k)` taken from the same costs:
//!   `|k − k_R(x − d)| > lr_max_diff` → NaN.
//! - **Speckles** ([`speckle_filter`]): 4-connected regions whose neighbouring disparities
//!   differ by at most `speckle_range` px and that have at most `speckle_window_size` pixels
//!   become NaN.
//!
//! Reference: H. Hirschmüller, "Stereo Processing by Semiglobal Matching and Mutual
//! Information", IEEE TPAMI 30(2), 2008; R. Zabih and J. Woodfill, "Non-parametric local
//! transforms for computing visual correspondence", ECCV 1994 (census).

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;
use std::sync::{Mutex, PoisonError};

use crate::filter::grayscale::{LumaStandard, grayscale};

/// Census costs are Hamming distances times this, so that P1 and P2 can be set in quarter bits.
pub const COST_SCALE: u16 = 4;
/// Largest census window side: its `side² − 1` bits must fit in a u64.
pub const MAX_CENSUS_BLOCK: usize = 7;
/// Rows per parallel task of the per-row stages.
const ROWS_PER_TASK: usize = 4;

param_enum! {
    /// The matching algorithm.
    pub enum StereoMethod {
        /// Semi-global matching: census costs aggregated along 8 (or 4) paths.
        Sgm = "sgm",
        /// Block matching: the best window cost per pixel, no smoothness term.
        Bm = "bm",
    }
}

param_enum! {
    /// How the winner is refined below a pixel.
    pub enum SubpixelFit {
        /// "parabola" for ZNCC, "equiangular" for census and SAD.
        Auto = "auto",
        /// The parabola through the three costs around the winner.
        Parabola = "parabola",
        /// Two lines of opposite slope through them (Shimizu & Okutomi 2001): unbiased for
        /// V-shaped cost curves such as census and SAD, where the parabola pulls towards whole
        /// pixels.
        Equiangular = "equiangular",
    }
}

param_enum! {
    /// The matching cost.
    pub enum MatchCost {
        /// Hamming distance of census words over the block window (SGM and BM).
        Census = "census",
        /// Sum of absolute differences over the block window (BM).
        Sad = "sad",
        /// 1 − zero-mean normalised cross-correlation over the block window (BM); invariant to
        /// gain and offset between the views.
        Zncc = "zncc",
    }
}

params! {
    /// Parameters of `sfm.stereo`.
    pub struct StereoParams {
        /// Smallest disparity searched, px (left x ↔ right x − d). Default 0.
        min_disparity: i32 = 0 => [min = -100000, max = 100000, unit = "px"],
        /// Number of disparities searched: min_disparity … min_disparity + num_disparities − 1.
        /// Default 64.
        num_disparities: u32 = 64 => [min = 1, max = 8192, unit = "px"],
        /// Side of the matching window (odd), px: the census window, or the SAD/ZNCC block.
        /// Census allows at most 7. Default 5.
        block_size: u32 = 5 => [min = 1, max = 51, unit = "px"],
        /// "sgm" (semi-global matching) or "bm" (block matching). Default "sgm".
        method: StereoMethod = StereoMethod::Sgm,
        /// "census" (SGM and BM), "sad" or "zncc" (BM only). Default "census".
        cost: MatchCost = MatchCost::Census,
        /// SGM penalty for a ±1 px disparity change between neighbours along a path, in census
        /// bits (one bit = one differing neighbour of a census window of 25 bits for
        /// block_size 5). Default 2.
        p1: f64 = 2.0 => [min = 0.0, max = 1000.0, unit = "bits"],
        /// SGM penalty for a larger disparity jump, census bits, ≥ p1;
        /// `paths · (block_size² − 1 + p2) · 4` must stay below 65536. Default 16.
        p2: f64 = 16.0 => [min = 0.0, max = 1000.0, unit = "bits"],
        /// SGM aggregation paths: 8 (horizontal, vertical, diagonal) or 4 (horizontal and
        /// vertical only, faster). Default 8.
        paths: u32 = 8 => [min = 4, max = 8],
        /// A winner is rejected when another disparity more than 1 px away costs less than
        /// winner · 100 / (100 − uniqueness_ratio), percent; 0 disables. Default 10.
        uniqueness_ratio: f64 = 10.0 => [min = 0.0, max = 99.0, unit = "%"],
        /// Left–right consistency: the largest difference, px, between the left winner and
        /// the right view's winner at the matched pixel; negative disables. Default 1.
        lr_max_diff: f64 = 1.0 => [unit = "px"],
        /// Refine each winner below a pixel from its cost and its neighbours'. Default true.
        subpixel: bool = true,
        /// The subpixel fit: "auto" (parabola for ZNCC, equiangular for census and SAD),
        /// "parabola" or "equiangular". Default "auto".
        subpixel_fit: SubpixelFit = SubpixelFit::Auto,
        /// Regions (4-connected, neighbours within speckle_range) of at most this many pixels
        /// become NaN; 0 disables. Default 100.
        speckle_window_size: u32 = 100 => [unit = "px"],
        /// Largest disparity difference between neighbours of one speckle region, px. Default 2.
        speckle_range: f64 = 2.0 => [min = 0.0, unit = "px"],
    }
}

/// Checked options of [`disparity_map`].
#[derive(Debug, Clone, PartialEq)]
pub struct StereoOptions {
    /// Smallest disparity, px.
    pub min_disparity: i32,
    /// Number of disparities (≥ 1).
    pub num_disparities: usize,
    /// Window side (odd).
    pub block_size: usize,
    /// SGM or BM.
    pub method: StereoMethod,
    /// Matching cost.
    pub cost: MatchCost,
    /// SGM P1 in internal cost units (bits × [`COST_SCALE`]).
    pub p1: u16,
    /// SGM P2 in internal cost units.
    pub p2: u16,
    /// 8 or 4.
    pub paths: usize,
    /// Percent; 0 disables.
    pub uniqueness_ratio: f64,
    /// Px; negative disables.
    pub lr_max_diff: f64,
    /// Subpixel refinement.
    pub subpixel: bool,
    /// The subpixel fit ("auto" resolved when checked).
    pub subpixel_fit: SubpixelFit,
    /// Pixels; 0 disables.
    pub speckle_window_size: usize,
    /// Px.
    pub speckle_range: f64,
}

impl Default for StereoOptions {
    fn default() -> Self {
        // The defaults of the params are valid.
        match StereoOptions::from_params(&StereoParams::default()) {
            Ok(o) => o,
            Err(e) => unreachable!("default stereo params are invalid: {e}"),
        }
    }
}

impl StereoOptions {
    /// Checks `p` and converts it.
    pub fn from_params(p: &StereoParams) -> Result<StereoOptions, String> {
        let block = p.block_size as usize;
        if block.is_multiple_of(2) {
            return Err(format!("`block_size` must be odd, got {block}"));
        }
        if p.cost == MatchCost::Census && !(3..=MAX_CENSUS_BLOCK).contains(&block) {
            return Err(format!(
                "the census window is 3 to {MAX_CENSUS_BLOCK} px (its bits fill a 64-bit word), got block_size {block}"
            ));
        }
        if p.method == StereoMethod::Sgm && p.cost != MatchCost::Census {
            return Err(format!(
                "method \"sgm\" matches with cost \"census\"; \"{}\" is for method \"bm\"",
                p.cost.name()
            ));
        }
        if p.paths != 8 && p.paths != 4 {
            return Err(format!("`paths` must be 8 or 4, got {}", p.paths));
        }
        if !(p.p1.is_finite() && p.p2.is_finite() && p.p1 >= 0.0 && p.p2 >= p.p1) {
            return Err(format!(
                "the SGM penalties must satisfy 0 ≤ p1 ≤ p2, got p1 {} and p2 {}",
                p.p1, p.p2
            ));
        }
        let scale = f64::from(COST_SCALE);
        let (p1, p2) = ((p.p1 * scale).round(), (p.p2 * scale).round());
        let c_max = ((block * block - 1) as f64) * scale;
        let bound = f64::from(p.paths) * (c_max + p2);
        if bound >= f64::from(u16::MAX) {
            return Err(format!(
                "p2 {} is too large: paths · (census bits + p2) · {COST_SCALE} = {bound} must stay below 65535",
                p.p2
            ));
        }
        if !(p.uniqueness_ratio.is_finite() && (0.0..100.0).contains(&p.uniqueness_ratio)) {
            return Err(format!(
                "`uniqueness_ratio` must be in [0, 100), got {}",
                p.uniqueness_ratio
            ));
        }
        if !p.lr_max_diff.is_finite() || !p.speckle_range.is_finite() || p.speckle_range < 0.0 {
            return Err(
                "`lr_max_diff` and `speckle_range` must be finite, speckle_range ≥ 0".into(),
            );
        }
        Ok(StereoOptions {
            min_disparity: p.min_disparity,
            num_disparities: p.num_disparities as usize,
            block_size: block,
            method: p.method,
            cost: p.cost,
            p1: p1 as u16,
            p2: p2 as u16,
            paths: p.paths as usize,
            uniqueness_ratio: p.uniqueness_ratio,
            lr_max_diff: p.lr_max_diff,
            subpixel: p.subpixel,
            subpixel_fit: match (p.subpixel_fit, p.cost) {
                (SubpixelFit::Auto, MatchCost::Zncc) => SubpixelFit::Parabola,
                (SubpixelFit::Auto, _) => SubpixelFit::Equiangular,
                (fit, _) => fit,
            },
            speckle_window_size: p.speckle_window_size as usize,
            speckle_range: p.speckle_range,
        })
    }
}

/// Why a disparity map could not be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StereoError {
    /// An image has no pixels.
    #[error("the images are empty ({width}×{height})")]
    Empty {
        /// Width.
        width: usize,
        /// Height.
        height: usize,
    },
    /// The two views differ in size.
    #[error("the views differ in size: left {left_w}×{left_h}, right {right_w}×{right_h}")]
    SizeMismatch {
        /// Left width.
        left_w: usize,
        /// Left height.
        left_h: usize,
        /// Right width.
        right_w: usize,
        /// Right height.
        right_h: usize,
    },
    /// The aggregation volume would not fit in memory addresses.
    #[error("the cost volume {width}×{height}×{disparities} is too large")]
    TooLarge {
        /// Width.
        width: usize,
        /// Height.
        height: usize,
        /// Disparities.
        disparities: usize,
    },
    /// The planes do not hold width × height samples.
    #[error("a plane holds {got} samples, expected {expected}")]
    BadPlane {
        /// Samples held.
        got: usize,
        /// Samples expected.
        expected: usize,
    },
}

/// The range `[k_lo, k_hi)` of disparity indices whose right pixel `x − min_d − k` lies in
/// `[0, w)` (empty when none does).
fn valid_range(x: usize, w: usize, min_d: i32, n: usize) -> (usize, usize) {
    let at0 = x as i64 - i64::from(min_d);
    let lo = (at0 - (w as i64 - 1)).clamp(0, n as i64) as usize;
    let hi = (at0 + 1).clamp(0, n as i64) as usize;
    (lo, hi.max(lo))
}

/// Census words of a `w × h` plane with a `block × block` window (odd, ≤ 7): bit `i` is set
/// when the `i`-th neighbour (row-major, centre skipped) is darker than the centre. Samples
/// outside the image repeat the nearest border sample.
pub fn census(plane: &[f32], w: usize, h: usize, block: usize) -> Vec<u64> {
    let r = block / 2;
    let mut out = vec![0u64; w * h];
    if w == 0 || h == 0 {
        return out;
    }
    let pw = w + 2 * r;
    out.par_chunks_mut(w).enumerate().for_each_init(
        || vec![0f32; block * pw],
        |rows, (y, word_row)| {
            // The window's rows, padded by r on both sides with the border samples.
            for (i, dst) in rows.chunks_exact_mut(pw).enumerate() {
                let sy = (y + i).saturating_sub(r).min(h - 1);
                let src = &plane[sy * w..(sy + 1) * w];
                for (px, d) in dst.iter_mut().enumerate() {
                    *d = src[px.saturating_sub(r).min(w - 1)];
                }
            }
            census_row(rows, pw, w, block, word_row);
        },
    );
    out
}

/// The census words of one row from its `block` padded window rows (`pw` samples each):
/// one pass over the row per neighbour, so that the comparisons vectorize over x.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl",
    "x86_64+avx2",
    "x86_64+sse4.1"
))]
fn census_row(rows: &[f32], pw: usize, w: usize, block: usize, out: &mut [u64]) {
    let r = block / 2;
    let centre = &rows[r * pw + r..r * pw + r + w];
    let out = &mut out[..w];
    let mut bit = 0;
    for dy in 0..block {
        for dx in 0..block {
            if dy == r && dx == r {
                continue;
            }
            let nb = &rows[dy * pw + dx..dy * pw + dx + w];
            for ((word, &c), &v) in out.iter_mut().zip(centre).zip(nb) {
                *word |= u64::from(v < c) << bit;
            }
            bit += 1;
        }
    }
}

/// Census costs of pixels `x0 .. x0 + out.len() / n` of one row: `out[i·n + k]` is the Hamming
/// distance between the left word at `x0 + i` and the right word at `x0 + i − min_d − k`,
/// times [`COST_SCALE`]; `invalid` where that right pixel is outside the row.
#[multiversion::multiversion(targets("x86_64+avx2+popcnt", "x86_64+sse4.2+popcnt"))]
fn census_cost_row(
    left: &[u64],
    right: &[u64],
    x0: usize,
    min_d: i32,
    n: usize,
    invalid: u8,
    out: &mut [u8],
) {
    let w = left.len();
    for (i, o) in out.chunks_exact_mut(n).enumerate() {
        let x = x0 + i;
        let (lo, hi) = valid_range(x, w, min_d, n);
        o[..lo].fill(invalid);
        o[hi..].fill(invalid);
        if lo < hi {
            let c = left[x];
            // k ↔ right pixel x − min_d − k: k = lo … hi − 1 reads right pixels downwards.
            let first = (x as i64 - i64::from(min_d) - (hi as i64 - 1)) as usize;
            let src = &right[first..first + (hi - lo)];
            for (dst, &rw) in o[lo..hi].iter_mut().zip(src.iter().rev()) {
                *dst = ((c ^ rw).count_ones() as u8).wrapping_mul(COST_SCALE as u8);
            }
        }
    }
}

/// One SGM step along a path (Hirschmüller 2008, eq. 13, with the minimum subtracted):
/// `out[1 + k] = cost[k] + min(prev[1+k], prev[k] + p1, prev[2+k] + p1, prev_min + p2) −
/// prev_min`, and `acc[k] += out[1 + k]`. `prev` and `out` hold `n + 2` values, the first and
/// last being sentinels (`u16::MAX`). Returns `min_k out[1 + k]`.
// Indexing (not zipped iterators) over slices cut to one length keeps this loop
// bounds-check free and vectorized over k in u16 lanes.
#[allow(clippy::needless_range_loop)]
#[multiversion::multiversion(targets("x86_64+avx2", "x86_64+sse4.1"))]
pub fn sgm_step(
    cost: &[u8],
    prev: &[u16],
    prev_min: u16,
    p1: u16,
    p2: u16,
    out: &mut [u16],
    acc: &mut [u16],
) -> u16 {
    let n = cost.len();
    let (lower, centre, upper) = (&prev[..n], &prev[1..n + 1], &prev[2..n + 2]);
    let out = &mut out[1..n + 1];
    let acc = &mut acc[..n];
    let jump = prev_min.saturating_add(p2);
    let mut m = u16::MAX;
    for k in 0..n {
        let best = centre[k]
            .min(lower[k].saturating_add(p1))
            .min(upper[k].saturating_add(p1))
            .min(jump);
        let v = (best - prev_min).wrapping_add(u16::from(cost[k]));
        out[k] = v;
        acc[k] = acc[k].wrapping_add(v);
        m = m.min(v);
    }
    m
}

/// A path state before its first pixel: zeros between sentinels, so that the first step gives
/// `L_r = C`.
fn path_start(n: usize) -> Vec<u16> {
    let mut v = vec![0u16; n + 2];
    v[0] = u16::MAX;
    v[n + 1] = u16::MAX;
    v
}

/// Multiversion targets of the SGM kernels: integer code, so every path computes the same.
/// AVX-512BW doubles the u16 lanes of AVX2, and BITALG counts the bits of 64 census bytes in
/// one instruction.
macro_rules! sgm_kernel {
    ($item:item) => {
        #[multiversion::multiversion(targets(
            "x86_64+avx512f+avx512bw+avx512vl+avx512bitalg",
            "x86_64+avx2",
            "x86_64+sse4.1"
        ))]
        $item
    };
}

/// The inputs of both SGM sweeps.
struct SweepContext<'a> {
    /// Left census words, `w × h`.
    left: &'a [u64],
    /// The right census words as byte planes with columns reversed, `[y][plane][j]`: byte
    /// `plane` of the right word at column `w − 1 − j`. The right pixels `x − min_d − k` of
    /// `k = lo … hi − 1` are then one ascending run of `j`, and the Hamming distance is a sum of
    /// byte popcounts, which vectorizes in u8 lanes.
    right_planes: &'a [u8],
    /// Bytes per census word (1 for a 3 × 3 window, 3 for 5 × 5, 6 for 7 × 7).
    planes: usize,
    w: usize,
    h: usize,
    n: usize,
    min_d: i32,
    invalid: u8,
    p1: u16,
    p2: u16,
    /// 8 paths (horizontal and three from the previous row per sweep) or 4 (horizontal and
    /// vertical).
    diagonals: bool,
}

/// The right census words of a `w × h` plane as `planes` byte planes per row, columns
/// reversed (see [`SweepContext::right_planes`]).
fn reversed_byte_planes(words: &[u64], w: usize, planes: usize) -> Vec<u8> {
    let mut out = vec![0u8; words.len() * planes];
    if w == 0 {
        return out;
    }
    out.par_chunks_mut(w * planes)
        .zip(words.par_chunks(w))
        .for_each(|(dst, row)| {
            for (p, plane) in dst.chunks_exact_mut(w).enumerate() {
                for (b, &word) in plane.iter_mut().zip(row.iter().rev()) {
                    *b = (word >> (8 * p)) as u8;
                }
            }
        });
    out
}

/// Census costs of left pixel `x` against every disparity, as [`census_cost_row`] computes
/// them: `out[k]` for `min_d + k`, `invalid` where the right pixel is outside the row.
/// `right_rev` holds the row's right words as byte planes with reversed columns.
#[inline(always)]
fn census_cost_pixel(
    word: u64,
    right_rev: &[u8],
    w: usize,
    x: usize,
    min_d: i32,
    invalid: u8,
    out: &mut [u8],
) {
    let n = out.len();
    let (lo, hi) = valid_range(x, w, min_d, n);
    out[..lo].fill(invalid);
    out[hi..].fill(invalid);
    if lo >= hi {
        return;
    }
    // Disparity k ↔ right column x − min_d − k ↔ reversed column w − 1 − x + min_d + k.
    let start = (w as i64 - 1 - x as i64 + i64::from(min_d) + lo as i64) as usize;
    let o = &mut out[lo..hi];
    let bytes = word.to_le_bytes();
    // One pass over the disparities with every plane's bytes at once (1, 3 or 6 planes for
    // the census windows 3, 5 and 7).
    match right_rev.len() / w {
        1 => popcount_planes::<1>(bytes, right_rev, w, start, o),
        3 => popcount_planes::<3>(bytes, right_rev, w, start, o),
        6 => popcount_planes::<6>(bytes, right_rev, w, start, o),
        _ => {
            o.fill(0);
            let len = o.len();
            for (plane, &b) in right_rev.chunks_exact(w).zip(&bytes) {
                for (d, &s) in o.iter_mut().zip(&plane[start..start + len]) {
                    *d += (b ^ s).count_ones() as u8;
                }
            }
            for d in o.iter_mut() {
                *d = d.wrapping_mul(COST_SCALE as u8);
            }
        }
    }
}

/// `o[k] = COST_SCALE · Σ_p popcount(bytes[p] ^ plane_p[start + k])` over `PL` byte planes of
/// `w` bytes each.
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn popcount_planes<const PL: usize>(
    bytes: [u8; 8],
    right_rev: &[u8],
    w: usize,
    start: usize,
    o: &mut [u8],
) {
    let len = o.len();
    let src: [&[u8]; PL] = std::array::from_fn(|p| &right_rev[p * w + start..p * w + start + len]);
    for k in 0..len {
        let mut c = 0u8;
        for p in 0..PL {
            c += (bytes[p] ^ src[p][k]).count_ones() as u8;
        }
        o[k] = c.wrapping_mul(COST_SCALE as u8);
    }
}

/// `P` SGM steps of one pixel fused into one pass over the disparities: for each path `p`,
/// what [`sgm_step`] computes from `prev[p]`, `prev_min[p]` into `out[p]`, with the sum of the
/// `P` new costs written to `sum` (or added to it, `ADD`). The cost is loaded once, the sum
/// stored once. Returns the minima of the new costs.
// Indexing (not zipped iterators) over slices cut to one length keeps the loop bounds-check
// free and vectorized over k in u16 lanes; the loop over p is unrolled.
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn sgm_steps<const P: usize, const ADD: bool>(
    cost: &[u8],
    prev: [&[u16]; P],
    prev_min: [u16; P],
    p1: u16,
    p2: u16,
    out: [&mut [u16]; P],
    sum: &mut [u16],
) -> [u16; P] {
    let n = cost.len();
    let sum = &mut sum[..n];
    let lower = prev.map(|p| &p[..n]);
    let centre = prev.map(|p| &p[1..n + 1]);
    let upper = prev.map(|p| &p[2..n + 2]);
    let out = out.map(|o| &mut o[1..n + 1]);
    let jump = prev_min.map(|m| m.saturating_add(p2));
    let mut mins = [u16::MAX; P];
    for k in 0..n {
        let c = u16::from(cost[k]);
        let mut s = if ADD { sum[k] } else { 0 };
        for p in 0..P {
            let best = centre[p][k]
                .min(lower[p][k].saturating_add(p1))
                .min(upper[p][k].saturating_add(p1))
                .min(jump[p]);
            // best ≥ prev_min: every candidate is (see `sgm_step`).
            let v = best.wrapping_sub(prev_min[p]).wrapping_add(c);
            out[p][k] = v;
            s = s.wrapping_add(v);
            mins[p] = mins[p].min(v);
        }
        sum[k] = s;
    }
    mins
}

/// The path states of one sweep: the horizontal path's last pixel, and per pixel of the
/// previous row the states of the paths coming from it.
struct SweepState {
    /// `n + 2` values per state: sentinels around the costs of the `n` disparities.
    dp: usize,
    /// The horizontal path at the previous pixel of the row, and the one being written.
    h_prev: Vec<u16>,
    h_cur: Vec<u16>,
    /// `[path][x][dp]` for the paths from the previous row (3 with diagonals, else 1), of the
    /// previous row and of the current one; their minima `[path][x]`.
    prev: Vec<u16>,
    cur: Vec<u16>,
    prev_min: Vec<u16>,
    cur_min: Vec<u16>,
    /// The state before the first pixel of a path: zeros between sentinels.
    zero: Vec<u16>,
    cost: Vec<u8>,
}

impl SweepState {
    fn new(c: &SweepContext<'_>) -> SweepState {
        let dirs = if c.diagonals { 3 } else { 1 };
        let zero = path_start(c.n);
        // Every state starts as `zero`, so the first row needs no special case; the sentinels
        // are never overwritten.
        let rows: Vec<u16> = (0..dirs * c.w).flat_map(|_| zero.iter().copied()).collect();
        SweepState {
            dp: c.n + 2,
            h_prev: zero.clone(),
            h_cur: zero.clone(),
            prev: rows.clone(),
            cur: rows,
            prev_min: vec![0; dirs * c.w],
            cur_min: vec![0; dirs * c.w],
            zero,
            cost: vec![0; c.n],
        }
    }
}

/// One row of a sweep with `P` paths (the horizontal one first): costs of every pixel, the
/// path steps in the sweep's direction along the row, and the sum of the `P` paths written to
/// `sum` (the row's `w × n` aggregated costs) or added to it (`ADD`).
#[inline(always)]
fn sweep_row_paths<const P: usize, const ADD: bool>(
    c: &SweepContext<'_>,
    y: usize,
    down: bool,
    st: &mut SweepState,
    sum: &mut [u16],
) {
    let (w, n, dp) = (c.w, c.n, st.dp);
    let lrow = &c.left[y * w..(y + 1) * w];
    let rrow = &c.right_planes[y * w * c.planes..(y + 1) * w * c.planes];
    let mut h_min = 0u16;
    for i in 0..w {
        // Downward sweeps run left to right, upward ones right to left (the two horizontal
        // paths); the paths from the previous row read only that row, so order is free there.
        let x = if down { i } else { w - 1 - i };
        census_cost_pixel(lrow[x], rrow, w, x, c.min_d, c.invalid, &mut st.cost);
        let (prev, prev_min, zero) = (&st.prev, &st.prev_min, &st.zero);
        // Path p ≥ 1 comes from column x + shift of the previous row (none at the borders).
        let source = |p: usize| {
            let shift = if P == 4 { p as isize - 2 } else { 0 };
            let xs = x as isize + shift;
            (xs >= 0 && (xs as usize) < w).then(|| (p - 1) * w + xs as usize)
        };
        let prevs: [&[u16]; P] = std::array::from_fn(|p| match p {
            0 if i > 0 => &st.h_prev[..],
            0 => &zero[..],
            _ => source(p).map_or(&zero[..], |at| &prev[at * dp..(at + 1) * dp]),
        });
        let mins: [u16; P] = std::array::from_fn(|p| match p {
            0 if i > 0 => h_min,
            0 => 0,
            _ => source(p).map_or(0, |at| prev_min[at]),
        });
        let mut h_out = Some(&mut st.h_cur[..]);
        let mut rows = st.cur.chunks_exact_mut(w * dp);
        let outs: [&mut [u16]; P] = std::array::from_fn(|p| {
            if p == 0 {
                h_out.take().unwrap_or_default()
            } else {
                rows.next()
                    .map(|r| &mut r[x * dp..(x + 1) * dp])
                    .unwrap_or_default()
            }
        });
        let new_min = sgm_steps::<P, ADD>(
            &st.cost,
            prevs,
            mins,
            c.p1,
            c.p2,
            outs,
            &mut sum[x * n..(x + 1) * n],
        );
        h_min = new_min[0];
        for (p, &m) in new_min.iter().enumerate().skip(1) {
            st.cur_min[(p - 1) * w + x] = m;
        }
        std::mem::swap(&mut st.h_prev, &mut st.h_cur);
    }
    std::mem::swap(&mut st.prev, &mut st.cur);
    std::mem::swap(&mut st.prev_min, &mut st.cur_min);
}

sgm_kernel! {
/// [`sweep_row_paths`] for the context's path count; the one dispatch per row.
fn sweep_row<'a>(
    c: &SweepContext<'a>,
    y: usize,
    down: bool,
    add: bool,
    st: &mut SweepState,
    sum: &mut [u16],
) {
    match (c.diagonals, add) {
        (true, false) => sweep_row_paths::<4, false>(c, y, down, st, sum),
        (true, true) => sweep_row_paths::<4, true>(c, y, down, st, sum),
        (false, false) => sweep_row_paths::<2, false>(c, y, down, st, sum),
        (false, true) => sweep_row_paths::<2, true>(c, y, down, st, sum),
    }
}
}

/// One row of the aggregated volume and of the disparity map, shared by the two sweeps.
struct RowSlot<'a> {
    sum: &'a mut [u16],
    disp: &'a mut [f32],
    /// How many sweeps have added their paths: the second one completes the row and decides.
    visits: u8,
}

/// One sweep over all rows, top to bottom (`down`: the left-to-right path and the three from
/// the row above) or bottom to top (the others). The first sweep to reach a row writes its
/// paths' sum, the second adds its own and decides the row's disparities. Integer sums do not
/// depend on which sweep comes first, so the result does not depend on the threads.
fn sweep(c: &SweepContext<'_>, o: &StereoOptions, rows: &[Mutex<RowSlot<'_>>], down: bool) {
    let mut st = SweepState::new(c);
    let mut scratch = DecideScratch::new(c.w);
    for i in 0..c.h {
        let y = if down { i } else { c.h - 1 - i };
        // The lock is held for the whole row; the other sweep waits at most one row, where
        // the two meet. Neither sweep holds two locks or waits on other work meanwhile.
        let mut slot = rows[y].lock().unwrap_or_else(PoisonError::into_inner);
        let slot = &mut *slot;
        sweep_row(c, y, down, slot.visits > 0, &mut st, slot.sum);
        slot.visits += 1;
        if slot.visits == 2 {
            decide_sgm_row(slot.sum, c.w, o, slot.disp, &mut scratch);
        }
    }
}

/// The SGM disparity map (before the speckle filter) of census words `left`, `right`
/// (`w × h`): the 8 (or 4) paths run as two sweeps, down and up, at the same time when a
/// second thread is free; the volume of summed costs is written by the first sweep to reach a
/// row and completed by the second, which decides the row right away.
fn sgm_disparity(left: &[u64], right: &[u64], w: usize, h: usize, o: &StereoOptions) -> Vec<f32> {
    let n = o.num_disparities;
    let bits = o.block_size * o.block_size - 1;
    let planes = bits.div_ceil(8);
    let right_planes = reversed_byte_planes(right, w, planes);
    let ctx = SweepContext {
        left,
        right_planes: &right_planes,
        planes,
        w,
        h,
        n,
        min_d: o.min_disparity,
        invalid: (bits as u16 * COST_SCALE) as u8,
        p1: o.p1,
        p2: o.p2,
        diagonals: o.paths == 8,
    };
    let mut disp = vec![f32::NAN; w * h];
    // Every row is written by its first sweep before it is read.
    let mut sum = ocellus_engine::buffer::zeroed::<u16>(w * n * h);
    let rows: Vec<Mutex<RowSlot<'_>>> = sum
        .chunks_mut(w * n)
        .zip(disp.chunks_mut(w))
        .map(|(sum, disp)| {
            Mutex::new(RowSlot {
                sum,
                disp,
                visits: 0,
            })
        })
        .collect();
    rayon::join(
        || sweep(&ctx, o, &rows, true),
        || sweep(&ctx, o, &rows, false),
    );
    drop(rows);
    disp
}

/// Buffers of [`decide_sgm_row`], kept across rows.
struct DecideScratch {
    winner: Vec<usize>,
    /// The right view's best cost and its disparity index, by reversed column `w − 1 − x_r`.
    right_cost: Vec<u16>,
    right_k: Vec<u16>,
}

impl DecideScratch {
    fn new(w: usize) -> DecideScratch {
        DecideScratch {
            winner: vec![usize::MAX; w],
            right_cost: vec![u16::MAX; w],
            right_k: vec![0; w],
        }
    }
}

/// The first index of the smallest value of a non-empty slice, and the value.
#[inline(always)]
fn first_min_u16(s: &[u16]) -> (usize, u16) {
    // One vectorized pass: per lane the smallest value and the first block holding it
    // (strict `<`), then the first index among the lanes holding the overall minimum.
    const LANES: usize = 32;
    let mut value = [u16::MAX; LANES];
    let mut block = [0u16; LANES];
    let blocks = s.chunks_exact(LANES);
    let rest = blocks.remainder();
    for (b, chunk) in blocks.enumerate() {
        let b = b as u16;
        for i in 0..LANES {
            let better = chunk[i] < value[i];
            value[i] = if better { chunk[i] } else { value[i] };
            block[i] = if better { b } else { block[i] };
        }
    }
    let mut best = (usize::MAX, u16::MAX);
    for i in 0..LANES {
        let at = usize::from(block[i]) * LANES + i;
        if value[i] < best.1 || (value[i] == best.1 && at < best.0) {
            best = (at, value[i]);
        }
    }
    let base = s.len() - rest.len();
    for (i, &v) in rest.iter().enumerate() {
        if v < best.1 {
            best = (base + i, v);
        }
    }
    if best.0 == usize::MAX {
        best.0 = 0;
    }
    best
}

sgm_kernel! {
/// [`decide_row`] for the u16 SGM costs, with the same results: the winner scan and the right
/// view's winners vectorized over the disparities. The right view's winner at `x_r` is the
/// first `k` (smallest) of least cost among the left pixels `x = x_r + min_d + k`, the order
/// in which `decide_row` visits them.
fn decide_sgm_row(costs: &[u16], w: usize, o: &StereoOptions, out: &mut [f32], s: &mut DecideScratch) {
    let n = o.num_disparities;
    let min_d = o.min_disparity;
    for (x, (slot, dst)) in s.winner.iter_mut().zip(out.iter_mut()).enumerate() {
        *dst = f32::NAN;
        *slot = usize::MAX;
        let (lo, hi) = valid_range(x, w, min_d, n);
        if lo >= hi {
            continue;
        }
        let c = &costs[x * n..(x + 1) * n];
        let (i, best) = first_min_u16(&c[lo..hi]);
        let k = lo + i;
        if o.uniqueness_ratio > 0.0 {
            let below = c[lo..k.saturating_sub(1).max(lo)].iter().copied().min();
            let above = c[(k + 2).min(hi)..hi].iter().copied().min();
            let limit = f64::from(best) * 100.0;
            let keep = 100.0 - o.uniqueness_ratio;
            if [below, above]
                .into_iter()
                .flatten()
                .any(|v| f64::from(v) * keep <= limit)
            {
                continue;
            }
        }
        let mut d = f64::from(min_d) + k as f64;
        if o.subpixel && k > lo && k + 1 < hi {
            let (a, b, e) = (f64::from(c[k - 1]), f64::from(best), f64::from(c[k + 1]));
            let denom = match o.subpixel_fit {
                SubpixelFit::Parabola => a + e - 2.0 * b,
                _ => a.max(e) - b,
            };
            if denom > 0.0 {
                d += (a - e) / (2.0 * denom);
            }
        }
        *slot = k;
        *dst = d as f32;
    }
    if o.lr_max_diff < 0.0 {
        return;
    }
    // Every S < u16::MAX (the bound checked in `StereoOptions::from_params`), so the first
    // candidate of a right pixel always replaces the initial value.
    s.right_cost.fill(u16::MAX);
    s.right_k.fill(0);
    for x in 0..w {
        let (lo, hi) = valid_range(x, w, min_d, n);
        if lo >= hi {
            continue;
        }
        let start = (w as i64 - 1 - x as i64 + i64::from(min_d) + lo as i64) as usize;
        let len = hi - lo;
        let c = &costs[x * n + lo..x * n + hi];
        let best = &mut s.right_cost[start..start + len];
        let best_k = &mut s.right_k[start..start + len];
        let mut k = lo as u16;
        for ((&v, b), bk) in c.iter().zip(best.iter_mut()).zip(best_k.iter_mut()) {
            let better = v < *b;
            *b = if better { v } else { *b };
            *bk = if better { k } else { *bk };
            k = k.wrapping_add(1);
        }
    }
    for (x, (&k, dst)) in s.winner.iter().zip(out.iter_mut()).enumerate() {
        if k == usize::MAX {
            continue;
        }
        let xr = x as i64 - i64::from(min_d) - k as i64;
        let kr = s.right_k[(w as i64 - 1 - xr) as usize];
        if (f64::from(kr) - k as f64).abs() > o.lr_max_diff {
            *dst = f32::NAN;
        }
    }
}
}

/// Costs the decision can compare.
pub trait CostValue: Copy + PartialOrd + Send + Sync {
    /// As f64 (for the parabola and the uniqueness test).
    fn to_f64(self) -> f64;
    /// Whether the cost stands for a real match (finite).
    fn usable(self) -> bool;
    /// The smallest value of a slice, if any.
    fn min_of(s: &[Self]) -> Option<Self>;
}

impl CostValue for u16 {
    fn to_f64(self) -> f64 {
        f64::from(self)
    }
    fn usable(self) -> bool {
        true
    }
    fn min_of(s: &[u16]) -> Option<u16> {
        // `Iterator::min` on integers is a vectorized reduction.
        s.iter().copied().min()
    }
}

impl CostValue for f32 {
    fn to_f64(self) -> f64 {
        f64::from(self)
    }
    fn usable(self) -> bool {
        self.is_finite()
    }
    fn min_of(s: &[f32]) -> Option<f32> {
        s.iter().copied().reduce(|a, b| if b < a { b } else { a })
    }
}

/// The smallest cost of a non-empty slice and its first index.
fn argmin<T: CostValue>(s: &[T]) -> (usize, T) {
    let Some(m) = T::min_of(s) else {
        return (0, s[0]);
    };
    (s.iter().position(|&v| v == m).unwrap_or(0), m)
}

/// The smallest cost of a slice, if any.
fn min_cost<T: CostValue>(s: &[T]) -> Option<T> {
    T::min_of(s)
}

/// The winner-take-all decision for one row of costs `costs[x·n + k]` (see the module docs):
/// writes the disparity (px) or NaN per pixel into `out`.
pub fn decide_row<T: CostValue>(costs: &[T], w: usize, o: &StereoOptions, out: &mut [f32]) {
    let n = o.num_disparities;
    let min_d = o.min_disparity;
    let mut winner = vec![usize::MAX; w];
    for (x, (slot, dst)) in winner.iter_mut().zip(out.iter_mut()).enumerate() {
        *dst = f32::NAN;
        let (lo, hi) = valid_range(x, w, min_d, n);
        if lo >= hi {
            continue;
        }
        let c = &costs[x * n..(x + 1) * n];
        let (i, best) = argmin(&c[lo..hi]);
        if !best.usable() {
            continue;
        }
        let k = lo + i;
        if o.uniqueness_ratio > 0.0 {
            let below = min_cost(&c[lo..k.saturating_sub(1).max(lo)]);
            let above = min_cost(&c[(k + 2).min(hi)..hi]);
            let limit = best.to_f64() * 100.0;
            let keep = 100.0 - o.uniqueness_ratio;
            if [below, above]
                .into_iter()
                .flatten()
                .any(|v| v.to_f64() * keep <= limit)
            {
                continue;
            }
        }
        let mut d = f64::from(min_d) + k as f64;
        if o.subpixel && k > lo && k + 1 < hi {
            let (a, b, e) = (c[k - 1].to_f64(), best.to_f64(), c[k + 1].to_f64());
            if a.is_finite() && e.is_finite() {
                let denom = match o.subpixel_fit {
                    SubpixelFit::Parabola => a + e - 2.0 * b,
                    _ => a.max(e) - b,
                };
                if denom > 0.0 {
                    d += (a - e) / (2.0 * denom);
                }
            }
        }
        *slot = k;
        *dst = d as f32;
    }
    if o.lr_max_diff < 0.0 {
        return;
    }
    // The right view's winners from the same costs: right pixel x − min_d − k.
    let mut right_best: Vec<Option<(T, usize)>> = vec![None; w];
    for x in 0..w {
        let (lo, hi) = valid_range(x, w, min_d, n);
        let c = &costs[x * n..(x + 1) * n];
        for (k, &v) in c.iter().enumerate().take(hi).skip(lo) {
            if !v.usable() {
                continue;
            }
            let xr = (x as i64 - i64::from(min_d) - k as i64) as usize;
            let better = match right_best[xr] {
                Some((b, _)) => v < b,
                None => true,
            };
            if better {
                right_best[xr] = Some((v, k));
            }
        }
    }
    for (x, (&k, dst)) in winner.iter().zip(out.iter_mut()).enumerate() {
        if k == usize::MAX {
            continue;
        }
        let xr = (x as i64 - i64::from(min_d) - k as i64) as usize;
        let consistent =
            right_best[xr].is_some_and(|(_, kr)| (kr as f64 - k as f64).abs() <= o.lr_max_diff);
        if !consistent {
            *dst = f32::NAN;
        }
    }
}

/// `plane` (w × h) padded by `r` on every side, repeating border samples.
fn pad(plane: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
    let pw = w + 2 * r;
    let mut out = Vec::with_capacity(pw * (h + 2 * r));
    for py in 0..h + 2 * r {
        let y = py.saturating_sub(r).min(h - 1);
        let row = &plane[y * w..(y + 1) * w];
        for px in 0..pw {
            out.push(row[px.saturating_sub(r).min(w - 1)]);
        }
    }
    out
}

/// Window sums `Σv` and `Σv²` of every pixel of a padded plane (`w × h` pixels, padding `r`).
fn window_moments(padded: &[f32], w: usize, h: usize, r: usize) -> (Vec<f64>, Vec<f64>) {
    let pw = w + 2 * r;
    let b = 2 * r + 1;
    let mut s = vec![0f64; w * h];
    let mut s2 = vec![0f64; w * h];
    s.par_chunks_mut(w)
        .zip(s2.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (s, s2))| {
            for x in 0..w {
                let (mut a, mut a2) = (0f64, 0f64);
                for i in 0..b {
                    for &v in &padded[(y + i) * pw + x..(y + i) * pw + x + b] {
                        a += f64::from(v);
                        a2 += f64::from(v) * f64::from(v);
                    }
                }
                s[x] = a;
                s2[x] = a2;
            }
        });
    (s, s2)
}

/// Inputs of [`bm_costs_row`] prepared once per pair.
pub struct BmPlanes {
    w: usize,
    r: usize,
    left: Vec<f32>,
    right: Vec<f32>,
    census_left: Vec<u64>,
    census_right: Vec<u64>,
    /// ZNCC window sums of the left and right views.
    moments: Option<[(Vec<f64>, Vec<f64>); 2]>,
    /// Variances below this are treated as flat (no correlation defined).
    flat_variance: f64,
}

impl BmPlanes {
    /// Prepares gray planes `left`, `right` (`w × h`) for `o`.
    pub fn new(left: &[f32], right: &[f32], w: usize, h: usize, o: &StereoOptions) -> BmPlanes {
        let r = o.block_size / 2;
        let (census_left, census_right) = if o.cost == MatchCost::Census {
            (
                census(left, w, h, o.block_size),
                census(right, w, h, o.block_size),
            )
        } else {
            (Vec::new(), Vec::new())
        };
        let (lp, rp) = (pad(left, w, h, r), pad(right, w, h, r));
        let moments = (o.cost == MatchCost::Zncc)
            .then(|| [window_moments(&lp, w, h, r), window_moments(&rp, w, h, r)]);
        let peak = left
            .iter()
            .chain(right)
            .fold(0f64, |m, &v| m.max(f64::from(v).abs()));
        let b = (o.block_size * o.block_size) as f64;
        BmPlanes {
            w,
            r,
            left: lp,
            right: rp,
            census_left,
            census_right,
            moments,
            flat_variance: b * (1e-4 * peak.max(f64::MIN_POSITIVE)).powi(2),
        }
    }
}

/// Block-matching costs of row `y`: `out[x·n + k]` for disparity `min_d + k`, +∞ where the
/// right pixel is outside the image.
pub fn bm_costs_row(p: &BmPlanes, y: usize, o: &StereoOptions, out: &mut [f32]) {
    let (w, r, n) = (p.w, p.r, o.num_disparities);
    out.fill(f32::INFINITY);
    if o.cost == MatchCost::Census {
        let mut row = vec![0u8; w * n];
        census_cost_row(
            &p.census_left[y * w..(y + 1) * w],
            &p.census_right[y * w..(y + 1) * w],
            0,
            o.min_disparity,
            n,
            u8::MAX,
            &mut row,
        );
        for (x, (dst, src)) in out.chunks_exact_mut(n).zip(row.chunks_exact(n)).enumerate() {
            let (lo, hi) = valid_range(x, w, o.min_disparity, n);
            for k in lo..hi {
                dst[k] = f32::from(src[k]);
            }
        }
        return;
    }
    let pw = w + 2 * r;
    let b = 2 * r + 1;
    let mut column = vec![0f32; pw];
    let mut sums = vec![0f32; w];
    for k in 0..n {
        let dd = i64::from(o.min_disparity) + k as i64;
        // Padded columns whose right partner x' − dd is inside the padded row.
        let xa = dd.clamp(0, pw as i64) as usize;
        let xb = (pw as i64 + dd).clamp(0, pw as i64) as usize;
        if xa >= xb {
            continue;
        }
        column.fill(0.0);
        for i in 0..b {
            let lrow = &p.left[(y + i) * pw..(y + i + 1) * pw];
            let rrow = &p.right[(y + i) * pw..(y + i + 1) * pw];
            let ra = (xa as i64 - dd) as usize;
            let rs = &rrow[ra..ra + (xb - xa)];
            let dst = &mut column[xa..xb];
            match o.cost {
                MatchCost::Zncc => {
                    for ((c, &l), &rv) in dst.iter_mut().zip(&lrow[xa..xb]).zip(rs) {
                        *c += l * rv;
                    }
                }
                _ => {
                    for ((c, &l), &rv) in dst.iter_mut().zip(&lrow[xa..xb]).zip(rs) {
                        *c += (l - rv).abs();
                    }
                }
            }
        }
        // Output pixels whose right pixel x − dd is in [0, w).
        let x_lo = dd.clamp(0, w as i64) as usize;
        let x_hi = (w as i64 + dd).clamp(0, w as i64) as usize;
        if x_lo >= x_hi {
            continue;
        }
        let s = &mut sums[x_lo..x_hi];
        s.fill(0.0);
        for j in 0..b {
            for (a, &c) in s.iter_mut().zip(&column[x_lo + j..x_hi + j]) {
                *a += c;
            }
        }
        match &p.moments {
            Some([(sl, sl2), (sr, sr2)]) => {
                let count = (b * b) as f64;
                for (i, &lr) in s.iter().enumerate() {
                    let x = x_lo + i;
                    let xr = (x as i64 - dd) as usize;
                    let (a, a2) = (sl[y * w + x], sl2[y * w + x]);
                    let (c, c2) = (sr[y * w + xr], sr2[y * w + xr]);
                    let vl = a2 - a * a / count;
                    let vr = c2 - c * c / count;
                    let cost = if vl <= p.flat_variance || vr <= p.flat_variance {
                        1.0
                    } else {
                        let zncc = (f64::from(lr) - a * c / count) / (vl * vr).sqrt();
                        1.0 - zncc.clamp(-1.0, 1.0)
                    };
                    out[x * n + k] = cost as f32;
                }
            }
            None => {
                for (i, &v) in s.iter().enumerate() {
                    out[(x_lo + i) * n + k] = v;
                }
            }
        }
    }
}

/// Speckle filter: 4-connected regions (neighbours whose disparities differ by at most
/// `range` px) of at most `max_size` pixels become NaN. Returns how many pixels it cleared.
pub fn speckle_filter(disp: &mut [f32], w: usize, h: usize, max_size: usize, range: f64) -> usize {
    if max_size == 0 || w == 0 || h == 0 {
        return 0;
    }
    let mut label = vec![0u32; w * h];
    let mut stack = Vec::new();
    let mut region = Vec::new();
    let mut cleared = 0;
    let mut next = 0u32;
    for start in 0..w * h {
        if label[start] != 0 || disp[start].is_nan() {
            continue;
        }
        next += 1;
        label[start] = next;
        stack.push(start);
        region.clear();
        while let Some(p) = stack.pop() {
            region.push(p);
            let (x, y) = (p % w, p / w);
            let d = f64::from(disp[p]);
            let mut visit = |q: usize| {
                if label[q] == 0 && !disp[q].is_nan() && (f64::from(disp[q]) - d).abs() <= range {
                    label[q] = next;
                    stack.push(q);
                }
            };
            if x > 0 {
                visit(p - 1);
            }
            if x + 1 < w {
                visit(p + 1);
            }
            if y > 0 {
                visit(p - w);
            }
            if y + 1 < h {
                visit(p + w);
            }
        }
        if region.len() <= max_size {
            for &p in &region {
                disp[p] = f32::NAN;
            }
            cleared += region.len();
        }
    }
    cleared
}

/// The disparity map (`w × h`, px, NaN where none) of the gray planes `left`, `right`
/// (row-major, `w × h` each) with options `o`. See the module docs.
pub fn disparity_map(
    left: &[f32],
    right: &[f32],
    w: usize,
    h: usize,
    o: &StereoOptions,
) -> Result<Vec<f32>, StereoError> {
    if w == 0 || h == 0 {
        return Err(StereoError::Empty {
            width: w,
            height: h,
        });
    }
    for p in [left, right] {
        if p.len() != w * h {
            return Err(StereoError::BadPlane {
                got: p.len(),
                expected: w * h,
            });
        }
    }
    let n = o.num_disparities;
    let too_large = StereoError::TooLarge {
        width: w,
        height: h,
        disparities: n,
    };
    let row = w.checked_mul(n).ok_or(too_large.clone())?;
    let cells = row.checked_mul(h).ok_or(too_large.clone())?;
    if cells.checked_mul(4).is_none() {
        return Err(too_large);
    }
    let mut disp = match o.method {
        StereoMethod::Sgm => {
            let (cl, cr) = rayon::join(
                || census(left, w, h, o.block_size),
                || census(right, w, h, o.block_size),
            );
            sgm_disparity(&cl, &cr, w, h, o)
        }
        StereoMethod::Bm => {
            let mut disp = vec![f32::NAN; w * h];
            let planes = BmPlanes::new(left, right, w, h, o);
            disp.par_chunks_mut(w * ROWS_PER_TASK)
                .enumerate()
                .for_each(|(t, dst)| {
                    let mut costs = vec![0f32; row];
                    for (i, d) in dst.chunks_mut(w).enumerate() {
                        bm_costs_row(&planes, t * ROWS_PER_TASK + i, o, &mut costs);
                        decide_row(&costs, w, o, d);
                    }
                });
            disp
        }
    };
    speckle_filter(&mut disp, w, h, o.speckle_window_size, o.speckle_range);
    Ok(disp)
}

/// The gray f32 plane of an image (gray or RGB(A); u8, u16 or f32 samples kept in their units).
pub fn gray_plane(image: &Image) -> Result<Vec<f32>, String> {
    let gray = if image.channels() == Channels::Gray {
        image.clone()
    } else {
        grayscale(image, LumaStandard::Bt601).map_err(|e| e.to_string())?
    };
    Ok(match gray.data() {
        PixelData::U8(v) => v.iter().map(|&s| f32::from(s)).collect(),
        PixelData::U16(v) => v.iter().map(|&s| f32::from(s)).collect(),
        PixelData::F32(v) => v.to_vec(),
    })
}

/// Dense stereo (`sfm.stereo`). See [`disparity_map`].
#[derive(Debug, Clone, PartialEq)]
pub struct Stereo {
    options: StereoOptions,
}

impl Op for Stereo {
    type Params = StereoParams;
    const ID: &'static str = "sfm.stereo";
    const SUMMARY: &'static str =
        "Dense disparity of a rectified stereo pair: semi-global matching or block matching.";
    const DOC: &'static str = r#"
The disparity map of a rectified pair (`left`, `right`: same size, gray or RGB — converted to
gray with BT.601 weights — u8, u16 or f32). Output `disparity`: a gray f32 image in the left
view, in pixels, with left (x, y) ↔ right (x − d, y); NaN where no disparity survives.

Algorithm (`method`):
- "sgm" (default): census transform over a block_size × block_size window (≤ 7), Hamming
  costs (×4, u8) aggregated along 8 paths (or 4) by semi-global matching:
  L_r(p, d) = C(p, d) + min(L_r(p−r, d), L_r(p−r, d±1) + P1, min_k L_r(p−r, k) + P2)
  − min_k L_r(p−r, k), summed in u16 (Hirschmüller 2008, eq. 13). p1, p2 are in census bits:
  a window of block_size² − 1 bits costs at most that many bits per pixel. Peak memory: the
  summed volume, width · height · num_disparities · 2 bytes.
- "bm": the best window cost per pixel; cost "sad" (sum of absolute differences, in the
  image's units), "zncc" (1 − zero-mean normalised cross-correlation, invariant to gain and
  offset; flat windows cost 1) or "census" (Hamming bits).

Then per pixel: the winner over the disparities whose right pixel is inside the image; the
uniqueness test (another disparity more than 1 away within uniqueness_ratio % of the best
rejects it); subpixel refinement from the winner's cost and its neighbours' (subpixel_fit:
the parabola through them, or two lines of opposite slope — the default for census and SAD,
whose V-shaped curves the parabola biases towards whole pixels); the
left–right check against the right view's winner computed from the same costs (lr_max_diff
px); and the speckle filter (4-connected regions of ≤ speckle_window_size pixels whose
neighbours differ by ≤ speckle_range px become NaN). Deterministic: integer SGM arithmetic,
per-row work, identical for any thread count.

References: H. Hirschmüller, "Stereo Processing by Semiglobal Matching and Mutual
Information", IEEE TPAMI 2008; R. Zabih, J. Woodfill, "Non-parametric local transforms for
computing visual correspondence", ECCV 1994.

Example:
    "stereo": (op: "sfm.stereo", inputs: { "left": "left.image", "right": "right.image" },
               params: (min_disparity: 0, num_disparities: 64, block_size: 5)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "left",
                PortType::Image,
                "Left view of a rectified pair (gray or RGB; u8, u16 or f32).",
            ),
            PortSpec::new(
                "right",
                PortType::Image,
                "Right view, same size as the left.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "disparity",
            PortType::Image,
            "Disparity in the left view, gray f32, px (left x ↔ right x − d); NaN where none.",
        )]
    }

    fn new(params: StereoParams) -> Result<Self, String> {
        Ok(Stereo {
            options: StereoOptions::from_params(&params)?,
        })
    }
}

impl Operator for Stereo {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let left = inputs.image("left")?;
        let right = inputs.image("right")?;
        if (left.width(), left.height()) != (right.width(), right.height()) {
            return Err(OpError::input(
                "right",
                StereoError::SizeMismatch {
                    left_w: left.width(),
                    left_h: left.height(),
                    right_w: right.width(),
                    right_h: right.height(),
                }
                .to_string(),
            ));
        }
        let l = gray_plane(left).map_err(|e| OpError::input("left", e))?;
        let r = gray_plane(right).map_err(|e| OpError::input("right", e))?;
        let (w, h) = (left.width(), left.height());
        let disp = disparity_map(&l, &r, w, h, &self.options)
            .map_err(|e| OpError::input("left", e.to_string()))?;
        let out = Image::from_f32(w, h, Channels::Gray, disp)
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new().with("disparity", Value::image(out)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::randoms;
    use proptest::prelude::*;

    /// Options with the filters that would hide raw matching results switched off.
    fn raw(method: StereoMethod, cost: MatchCost, n: usize) -> StereoOptions {
        StereoOptions {
            method,
            cost,
            num_disparities: n,
            subpixel: false,
            speckle_window_size: 0,
            ..StereoOptions::default()
        }
    }

    /// A random texture `w × h` with samples in 0..256 (integers, as from u8 images).
    fn texture(w: usize, h: usize, seed: u64) -> Vec<f32> {
        randoms(seed, w * h)
            .iter()
            .map(|r| (r * 256.0).floor() as f32)
            .collect()
    }

    /// The pair of a fronto-parallel plane at integer disparity `d`: `left(x) = tex(x)`,
    /// `right(x) = tex(x + d)`, so that left x ↔ right x − d.
    fn shifted_pair(w: usize, h: usize, d: usize, seed: u64) -> (Vec<f32>, Vec<f32>) {
        let tw = w + d;
        let tex = texture(tw, h, seed);
        let mut left = vec![0f32; w * h];
        let mut right = vec![0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                left[y * w + x] = tex[y * tw + x];
                right[y * w + x] = tex[y * tw + x + d];
            }
        }
        (left, right)
    }

    /// A smooth 2-D texture evaluated anywhere: a sum of sinusoids of random frequency and phase.
    fn smooth(u: f64, y: f64, waves: &[[f64; 4]]) -> f32 {
        let v: f64 = waves
            .iter()
            .map(|[a, fx, fy, ph]| a * (fx * u + fy * y + ph).sin())
            .sum();
        (128.0 + v) as f32
    }

    fn waves(seed: u64) -> Vec<[f64; 4]> {
        randoms(seed, 48)
            .chunks_exact(4)
            .map(|r| {
                [
                    12.0 + 10.0 * r[0],
                    0.3 + 1.2 * r[1],
                    -1.0 + 2.0 * r[2],
                    6.3 * r[3],
                ]
            })
            .collect()
    }

    #[test]
    fn sgm_step_matches_hand_computation() {
        let m = u16::MAX;
        let cost = [4u8, 0, 8];
        let prev = [m, 0, 10, 30, m];
        let mut out = [m, 0, 0, 0, m];
        let mut acc = [100u16, 0, 0];
        let min = sgm_step(&cost, &prev, 0, 3, 20, &mut out, &mut acc);
        // k0: min(0, ∞, 10+3, 20) + 4; k1: min(10, 0+3, 30+3, 20) + 0; k2: min(30, 13, ∞, 20) + 8.
        assert_eq!(out, [m, 4, 3, 21, m]);
        assert_eq!(acc, [104, 3, 21]);
        assert_eq!(min, 3);
        // With a previous minimum the jump term is prev_min + p2, and prev_min is subtracted.
        let prev = [m, 50, 90, 95, m];
        let min = sgm_step(&[0, 0, 0], &prev, 50, 3, 20, &mut out, &mut acc);
        assert_eq!(out, [m, 0, 3, 20, m]);
        assert_eq!(min, 0);
    }

    #[test]
    fn census_of_a_ramp() {
        let plane: Vec<f32> = (1..=9).map(|v| v as f32).collect();
        let c = census(&plane, 3, 3, 3);
        // Centre 5: neighbours 1, 2, 3, 4 (bits 0–3) are darker.
        assert_eq!(c[4], 0b1111);
        // Corner 1 (borders repeat): no neighbour is darker.
        assert_eq!(c[0], 0);
        // Corner 9: neighbours 5, 6, 6 (row above, the last one replicated), 8 (left) and 8
        // (below left, replicated) are darker; the replicated 9s are not.
        assert_eq!(c[8], 0b10_1111);
    }

    #[test]
    fn integer_shift_is_recovered_exactly() {
        let (w, h, d) = (64, 32, 7);
        let (l, r) = shifted_pair(w, h, d, 3);
        for o in [
            raw(StereoMethod::Sgm, MatchCost::Census, 16),
            raw(StereoMethod::Bm, MatchCost::Sad, 16),
            raw(StereoMethod::Bm, MatchCost::Zncc, 16),
            raw(StereoMethod::Bm, MatchCost::Census, 16),
        ] {
            let disp = disparity_map(&l, &r, w, h, &o).unwrap();
            let mut matched = 0;
            // The last 2 columns' left windows repeat the border; their right windows do not.
            for y in 0..h {
                for x in d..w - 2 {
                    let v = disp[y * w + x];
                    if !v.is_nan() {
                        assert_eq!(v, d as f32, "{:?} {:?} at ({x}, {y})", o.method, o.cost);
                        matched += 1;
                    }
                }
            }
            let share = matched as f64 / ((w - 2 - d) * h) as f64;
            assert!(share > 0.95, "{:?} {:?}: density {share}", o.method, o.cost);
        }
    }

    #[test]
    fn bm_sad_and_zncc_agree_on_a_clean_pair() {
        let (w, h, d) = (48, 24, 5);
        let (l, r) = shifted_pair(w, h, d, 8);
        let sad = disparity_map(&l, &r, w, h, &raw(StereoMethod::Bm, MatchCost::Sad, 12)).unwrap();
        let zncc =
            disparity_map(&l, &r, w, h, &raw(StereoMethod::Bm, MatchCost::Zncc, 12)).unwrap();
        for y in 0..h {
            for x in d + 2..w - 2 {
                let (a, b) = (sad[y * w + x], zncc[y * w + x]);
                assert!(a == b, "({x}, {y}): sad {a}, zncc {b}");
            }
        }
    }

    #[test]
    fn zncc_is_invariant_to_gain_and_offset_of_the_right_view() {
        let (w, h, d) = (48, 24, 6);
        let (l, r) = shifted_pair(w, h, d, 21);
        let r2: Vec<f32> = r.iter().map(|v| 0.5 * v + 30.0).collect();
        let mut o = raw(StereoMethod::Bm, MatchCost::Zncc, 12);
        o.subpixel = true;
        let a = disparity_map(&l, &r, w, h, &o).unwrap();
        let b = disparity_map(&l, &r2, w, h, &o).unwrap();
        for (x, y) in a.iter().zip(&b) {
            assert_eq!(x.is_nan(), y.is_nan());
            if !x.is_nan() {
                assert!((x - y).abs() < 1e-3, "{x} vs {y}");
            }
        }
        let right = a.iter().filter(|v| (**v - d as f32).abs() < 0.5).count();
        assert!(right > w * h / 2, "{right} of {} matched", w * h);
    }

    #[test]
    fn fractional_shift_is_refined_below_a_pixel() {
        let (w, h) = (80, 40);
        let d = 6.3;
        let wv = waves(5);
        let mut l = vec![0f32; w * h];
        let mut r = vec![0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                l[y * w + x] = smooth(x as f64, y as f64, &wv);
                r[y * w + x] = smooth(x as f64 + d, y as f64, &wv);
            }
        }
        // Without refinement every error is 0.3 px. BM with ZNCC (smooth costs, parabola) gets
        // below 0.1 px; SGM's aggregated census costs stay biased towards whole pixels (median
        // 0.12 px measured with the equiangular fit, 0.16 px with the parabola).
        for (o, bound) in [
            (raw(StereoMethod::Bm, MatchCost::Zncc, 16), 0.1),
            (raw(StereoMethod::Sgm, MatchCost::Census, 16), 0.15),
        ] {
            let o = StereoOptions {
                subpixel: true,
                ..o
            };
            let disp = disparity_map(&l, &r, w, h, &o).unwrap();
            let mut errors: Vec<f64> = (4..h - 4)
                .flat_map(|y| (12..w - 4).map(move |x| (x, y)))
                .filter_map(|(x, y)| {
                    let v = disp[y * w + x];
                    (!v.is_nan()).then(|| (f64::from(v) - d).abs())
                })
                .collect();
            assert!(
                errors.len() > 1000,
                "{:?}: {} matched",
                o.method,
                errors.len()
            );
            errors.sort_by(f64::total_cmp);
            let median = errors[errors.len() / 2];
            let mean = errors.iter().sum::<f64>() / errors.len() as f64;
            assert!(
                median < bound && mean < 2.0 * bound,
                "{:?}: median {median}, mean {mean}",
                o.method
            );
        }
    }

    /// A fronto-parallel step: background at `d1` for x < w/2, a nearer textured object at
    /// `d2` for x ≥ w/2, both views rendered from the layers.
    fn step_pair(w: usize, h: usize, d1: usize, d2: usize) -> (Vec<f32>, Vec<f32>) {
        let span = w + d2;
        let bg = texture(span, h, 31);
        let fg = texture(span, h, 32);
        let (mut l, mut r) = (vec![0f32; w * h], vec![0f32; w * h]);
        for y in 0..h {
            for x in 0..w {
                // Scene coordinate u = left x; texture column u + d2 keeps indices ≥ 0.
                l[y * w + x] = if x >= w / 2 {
                    fg[y * span + x]
                } else {
                    bg[y * span + x]
                };
                // Right pixel x′ shows the object where x′ + d2 is on it, else the background.
                let u_fg = x + d2;
                r[y * w + x] = if (w / 2..w).contains(&u_fg) {
                    fg[y * span + u_fg]
                } else {
                    bg[y * span + x + d1]
                };
            }
        }
        (l, r)
    }

    #[test]
    fn step_edge_and_occlusion() {
        let (w, h, d1, d2) = (64, 32, 4, 12);
        let (l, r) = step_pair(w, h, d1, d2);
        let occluded = w / 2 - (d2 - d1)..w / 2;
        let mut o = raw(StereoMethod::Sgm, MatchCost::Census, 16);
        let disp = disparity_map(&l, &r, w, h, &o).unwrap();
        let (mut nan_occluded, mut total_occluded) = (0, 0);
        for y in 2..h - 2 {
            for x in 0..w {
                let v = disp[y * w + x];
                if (d1 + 3..occluded.start - 3).contains(&x) {
                    assert_eq!(v, d1 as f32, "background at ({x}, {y})");
                } else if (w / 2 + 3..w - 3).contains(&x) {
                    assert_eq!(v, d2 as f32, "object at ({x}, {y})");
                } else if occluded.contains(&x) {
                    total_occluded += 1;
                    nan_occluded += usize::from(v.is_nan());
                }
            }
        }
        assert!(
            nan_occluded * 10 >= total_occluded * 8,
            "{nan_occluded} of {total_occluded} occluded pixels are NaN"
        );
        // Without the left–right and uniqueness checks every pixel gets a disparity.
        o.lr_max_diff = -1.0;
        o.uniqueness_ratio = 0.0;
        let all = disparity_map(&l, &r, w, h, &o).unwrap();
        assert!(all.iter().all(|v| !v.is_nan()));
    }

    #[test]
    fn uniqueness_rejects_a_periodic_pattern() {
        // Period 6 along x: disparities 3, 9 and 15 match equally well.
        let (w, h, d, period) = (60, 20, 3, 6);
        let row = texture(period, h, 44);
        let tex = |x: usize, y: usize| row[y * period + x % period];
        let l: Vec<f32> = (0..w * h).map(|i| tex(i % w + d, i / w)).collect();
        let r: Vec<f32> = (0..w * h).map(|i| tex(i % w, i / w)).collect();
        let mut o = raw(StereoMethod::Bm, MatchCost::Sad, 18);
        let disp = disparity_map(&l, &r, w, h, &o).unwrap();
        let x0 = 16;
        let region = (0..h).flat_map(|y| (x0..w).map(move |x| y * w + x));
        let density = |d: &[f32]| {
            region.clone().filter(|&i| !d[i].is_nan()).count() as f64 / ((w - x0) * h) as f64
        };
        assert!(density(&disp) < 0.05, "density {}", density(&disp));
        o.uniqueness_ratio = 0.0;
        o.lr_max_diff = -1.0;
        let disp = disparity_map(&l, &r, w, h, &o).unwrap();
        assert!(density(&disp) > 0.99);
    }

    #[test]
    fn speckles_are_removed() {
        let (w, h) = (6, 5);
        let mut d = vec![10f32; w * h];
        d[7] = 30.0;
        d[8] = 30.5;
        d[20] = f32::NAN;
        let mut e = d.clone();
        assert_eq!(speckle_filter(&mut e, w, h, 3, 1.0), 2);
        assert!(e[7].is_nan() && e[8].is_nan() && e[20].is_nan());
        assert_eq!(e.iter().filter(|v| **v == 10.0).count(), w * h - 3);
        // A range of 25 px joins the island to the background: nothing is removed.
        let mut f = d.clone();
        assert_eq!(speckle_filter(&mut f, w, h, 3, 25.0), 0);
        assert_eq!(speckle_filter(&mut d, w, h, 0, 1.0), 0);
    }

    #[test]
    fn degenerate_sizes() {
        let o = StereoOptions::default();
        assert_eq!(
            disparity_map(&[], &[], 0, 4, &o),
            Err(StereoError::Empty {
                width: 0,
                height: 4
            })
        );
        assert!(matches!(
            disparity_map(&[1.0], &[1.0, 2.0], 1, 1, &o),
            Err(StereoError::BadPlane { .. })
        ));
        for method in [StereoMethod::Sgm, StereoMethod::Bm] {
            let o = StereoOptions {
                method,
                ..StereoOptions::default()
            };
            let one = disparity_map(&[7.0], &[7.0], 1, 1, &o).unwrap();
            assert_eq!(one.len(), 1);
            // Narrower than the search range: the 5 × 4 image still gets an answer.
            let (l, r) = shifted_pair(5, 4, 1, 2);
            assert_eq!(disparity_map(&l, &r, 5, 4, &o).unwrap().len(), 20);
        }
    }

    #[test]
    fn the_thread_count_does_not_change_the_result() {
        let (w, h) = (150, 40);
        let (l, r) = step_pair(w, h, 3, 11);
        let run = |threads: usize, o: &StereoOptions| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| disparity_map(&l, &r, w, h, o).unwrap())
                .iter()
                .map(|v| v.to_bits())
                .collect::<Vec<_>>()
        };
        for o in [
            StereoOptions {
                num_disparities: 20,
                ..StereoOptions::default()
            },
            StereoOptions {
                num_disparities: 20,
                method: StereoMethod::Bm,
                cost: MatchCost::Zncc,
                ..StereoOptions::default()
            },
        ] {
            assert_eq!(run(1, &o), run(3, &o));
        }
    }

    #[test]
    fn params_are_checked() {
        let check = |p: StereoParams| StereoOptions::from_params(&p);
        assert!(check(StereoParams::default()).is_ok());
        assert!(
            check(StereoParams {
                block_size: 4,
                ..StereoParams::default()
            })
            .is_err()
        );
        assert!(
            check(StereoParams {
                block_size: 9,
                ..StereoParams::default()
            })
            .is_err()
        );
        assert!(
            check(StereoParams {
                block_size: 9,
                method: StereoMethod::Bm,
                cost: MatchCost::Sad,
                ..StereoParams::default()
            })
            .is_ok()
        );
        assert!(
            check(StereoParams {
                cost: MatchCost::Sad,
                ..StereoParams::default()
            })
            .is_err()
        );
        assert!(
            check(StereoParams {
                p1: 20.0,
                p2: 10.0,
                ..StereoParams::default()
            })
            .is_err()
        );
        assert!(
            check(StereoParams {
                p2: 5000.0,
                ..StereoParams::default()
            })
            .is_err()
        );
        assert!(
            check(StereoParams {
                paths: 5,
                ..StereoParams::default()
            })
            .is_err()
        );
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        #[test]
        fn tiny_inputs_never_panic(
            w in 0usize..7, h in 0usize..7, min_d in -8i32..8, n in 1usize..24,
            bm in any::<bool>(), seed in 0u64..1000,
        ) {
            let o = StereoOptions {
                min_disparity: min_d,
                num_disparities: n,
                method: if bm { StereoMethod::Bm } else { StereoMethod::Sgm },
                cost: MatchCost::Census,
                block_size: 3,
                ..StereoOptions::default()
            };
            let l = texture(w, h, seed);
            let r = texture(w, h, seed + 1);
            match disparity_map(&l, &r, w, h, &o) {
                Ok(d) => {
                    prop_assert!(w > 0 && h > 0);
                    prop_assert_eq!(d.len(), w * h);
                    for v in d.iter().filter(|v| !v.is_nan()) {
                        let lo = min_d as f32 - 1.0;
                        prop_assert!(*v >= lo && *v <= lo + n as f32 + 1.0, "{}", v);
                    }
                }
                Err(e) => prop_assert!(w == 0 || h == 0, "{}", e),
            }
        }
    }

    /// The SGM volume as first written: each path in its own pass over the image (horizontal
    /// paths per row, the others row after row), every step by [`sgm_step`] — the reference the
    /// fused sweeps must reproduce exactly.
    fn reference_aggregate(
        left: &[u64],
        right: &[u64],
        w: usize,
        h: usize,
        o: &StereoOptions,
    ) -> Vec<u16> {
        let n = o.num_disparities;
        let row = w * n;
        let mut sum = vec![0u16; row * h];
        let invalid = (((o.block_size * o.block_size) - 1) as u16 * COST_SCALE) as u8;
        let (p1, p2) = (o.p1, o.p2);
        let mut cost = vec![0u8; row];
        let step = |x: usize, cost: &[u8], state: &mut (Vec<u16>, u16), acc: &mut [u16]| {
            let mut out = path_start(n);
            state.1 = sgm_step(
                &cost[x * n..(x + 1) * n],
                &state.0,
                state.1,
                p1,
                p2,
                &mut out,
                acc,
            );
            state.0 = out;
        };
        for y in 0..h {
            let (l, r) = (&left[y * w..(y + 1) * w], &right[y * w..(y + 1) * w]);
            census_cost_row(l, r, 0, o.min_disparity, n, invalid, &mut cost);
            let acc = &mut sum[y * row..(y + 1) * row];
            for xs in [(0..w).collect::<Vec<_>>(), (0..w).rev().collect()] {
                let mut state = (path_start(n), 0);
                for x in xs {
                    step(x, &cost, &mut state, &mut acc[x * n..(x + 1) * n]);
                }
            }
        }
        let shifts: &[isize] = if o.paths == 8 { &[-1, 0, 1] } else { &[0] };
        for &s in shifts {
            for down in [true, false] {
                let mut states = vec![(path_start(n), 0u16); w];
                for i in 0..h {
                    let y = if down { i } else { h - 1 - i };
                    let (l, r) = (&left[y * w..(y + 1) * w], &right[y * w..(y + 1) * w]);
                    census_cost_row(l, r, 0, o.min_disparity, n, invalid, &mut cost);
                    let mut next = Vec::with_capacity(w);
                    for x in 0..w {
                        let xs = x as isize + s;
                        let mut state = if i == 0 || xs < 0 || xs >= w as isize {
                            (path_start(n), 0)
                        } else {
                            states[xs as usize].clone()
                        };
                        let at = y * row + x * n;
                        step(x, &cost, &mut state, &mut sum[at..at + n]);
                        next.push(state);
                    }
                    states = next;
                }
            }
        }
        sum
    }

    /// [`disparity_map`] for SGM through the reference volume and the generic decision.
    fn reference_sgm(l: &[f32], r: &[f32], w: usize, h: usize, o: &StereoOptions) -> Vec<f32> {
        let (cl, cr) = (census(l, w, h, o.block_size), census(r, w, h, o.block_size));
        let sum = reference_aggregate(&cl, &cr, w, h, o);
        let n = o.num_disparities;
        let mut disp = vec![f32::NAN; w * h];
        for (d, c) in disp.chunks_mut(w).zip(sum.chunks(w * n)) {
            decide_row(c, w, o, d);
        }
        speckle_filter(&mut disp, w, h, o.speckle_window_size, o.speckle_range);
        disp
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|v| v.to_bits()).collect()
    }

    #[test]
    fn fused_steps_equal_single_steps() {
        let r = randoms(77, 4000);
        let mut at = 0;
        let mut next = |m: f64| {
            at += 1;
            (r[at % r.len()] * m) as u16
        };
        for n in [1, 5, 16, 31, 48, 67] {
            let cost: Vec<u8> = (0..n).map(|_| next(97.0) as u8).collect();
            let (p1, p2) = (next(20.0), 20 + next(100.0));
            let prev: Vec<Vec<u16>> = (0..4)
                .map(|_| {
                    let mut v = path_start(n);
                    for s in &mut v[1..n + 1] {
                        *s = next(400.0);
                    }
                    v
                })
                .collect();
            let prev_min: [u16; 4] =
                std::array::from_fn(|p| prev[p][1..n + 1].iter().copied().min().unwrap_or(0));
            let init: Vec<u16> = (0..n).map(|_| next(1000.0)).collect();
            // The reference: four single steps adding into `init`.
            let mut acc = init.clone();
            let mut want = Vec::new();
            for p in 0..4 {
                let mut out = path_start(n);
                let m = sgm_step(&cost, &prev[p], prev_min[p], p1, p2, &mut out, &mut acc);
                want.push((out, m));
            }
            for add in [false, true] {
                let mut outs: [Vec<u16>; 4] = std::array::from_fn(|_| path_start(n));
                let mut sum = init.clone();
                let [a, b, c, d] = &mut outs;
                let prevs = [&prev[0][..], &prev[1][..], &prev[2][..], &prev[3][..]];
                let outs_ref = [&mut a[..], &mut b[..], &mut c[..], &mut d[..]];
                let mins = if add {
                    sgm_steps::<4, true>(&cost, prevs, prev_min, p1, p2, outs_ref, &mut sum)
                } else {
                    sgm_steps::<4, false>(&cost, prevs, prev_min, p1, p2, outs_ref, &mut sum)
                };
                for p in 0..4 {
                    assert_eq!(outs[p], want[p].0, "n {n}, path {p}");
                    assert_eq!(mins[p], want[p].1);
                }
                let expected: Vec<u16> = if add {
                    acc.clone()
                } else {
                    (0..n).map(|k| acc[k].wrapping_sub(init[k])).collect()
                };
                assert_eq!(sum, expected, "n {n}, add {add}");
            }
        }
    }

    #[test]
    fn fast_decision_equals_the_generic_one() {
        // Costs from a small range make ties everywhere, in the left and the right winners.
        let (w, n) = (37, 19);
        for (seed, range) in [(1, 4.0), (2, 50.0), (3, 3000.0)] {
            let costs: Vec<u16> = randoms(seed, w * n)
                .iter()
                .map(|r| (r * range) as u16)
                .collect();
            for min_d in [-5, 0, 3, 30] {
                for (uniqueness_ratio, lr_max_diff) in
                    [(0.0, 0.0), (10.0, 1.0), (0.0, -1.0), (5.0, 2.5)]
                {
                    for fit in [SubpixelFit::Equiangular, SubpixelFit::Parabola] {
                        let o = StereoOptions {
                            min_disparity: min_d,
                            num_disparities: n,
                            uniqueness_ratio,
                            lr_max_diff,
                            subpixel_fit: fit,
                            ..StereoOptions::default()
                        };
                        let mut want = vec![0f32; w];
                        decide_row(&costs, w, &o, &mut want);
                        let mut got = vec![0f32; w];
                        decide_sgm_row(&costs, w, &o, &mut got, &mut DecideScratch::new(w));
                        assert_eq!(bits(&got), bits(&want), "{o:?}");
                    }
                }
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(40))]
        #[test]
        fn sgm_equals_the_reference_implementation(
            w in 1usize..40, h in 1usize..14, min_d in -12i32..20, n in 1usize..40,
            eight in any::<bool>(), block in prop::sample::select(vec![3usize, 5, 7]),
            p1 in 0u16..40, extra in 0u16..200, uniqueness in prop::sample::select(vec![0.0, 10.0]),
            lr in prop::sample::select(vec![-1.0, 0.0, 1.0, 2.0]), subpixel in any::<bool>(),
            shift in 0usize..12, noise in any::<bool>(), seed in 0u64..1000,
        ) {
            let o = StereoOptions {
                min_disparity: min_d,
                num_disparities: n,
                block_size: block,
                p1,
                p2: p1 + extra,
                paths: if eight { 8 } else { 4 },
                uniqueness_ratio: uniqueness,
                lr_max_diff: lr,
                subpixel,
                speckle_window_size: 3,
                ..StereoOptions::default()
            };
            // A shifted texture (real matches) or two unrelated ones.
            let (l, r) = if noise {
                (texture(w, h, seed), texture(w, h, seed + 1))
            } else {
                shifted_pair(w, h, shift, seed)
            };
            let got = disparity_map(&l, &r, w, h, &o).unwrap();
            prop_assert_eq!(bits(&got), bits(&reference_sgm(&l, &r, w, h, &o)));
        }
    }

    #[test]
    fn sgm_equals_the_reference_on_a_larger_scene() {
        // Wider than the 64-lane vectors, more disparities than one, a step edge with occlusion.
        let (w, h) = (150, 40);
        let (l, r) = step_pair(w, h, 3, 11);
        for (n, paths, min_d) in [(20, 8, 0), (67, 8, -3), (33, 4, 2)] {
            let o = StereoOptions {
                min_disparity: min_d,
                num_disparities: n,
                paths,
                p1: 12,
                p2: 150,
                uniqueness_ratio: 0.0,
                lr_max_diff: 2.0,
                ..StereoOptions::default()
            };
            let got = disparity_map(&l, &r, w, h, &o).unwrap();
            assert_eq!(bits(&got), bits(&reference_sgm(&l, &r, w, h, &o)), "n {n}");
            assert!(got.iter().filter(|v| !v.is_nan()).count() > w * h / 2);
        }
    }
}
