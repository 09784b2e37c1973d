//! AVX2 row kernel of [`super::fast::fast9`], written with intrinsics so that the sixteen
//! circle rows stay in registers (the portable kernel's arrays of lanes spill to the stack).
//!
//! Per vector of 32 centres it computes exactly what the portable `fast_vector` computes (the
//! corner test `max(B, D) > t` and the score `max(B, D) − 1`, saturated u8 arithmetic), with
//! two savings:
//! - the compass pretest is kept per polarity, and `B` (brighter arcs) or `D` (darker arcs) is
//!   computed only when some lane passes that polarity's pretest: a lane that fails it has no
//!   arc beyond `t` of that polarity, so the skipped value could never decide its test or
//!   score;
//! - the largest minimum over the sixteen circular windows of 9 is a van Herk/Gil-Werman
//!   pass over the circle unrolled to 24 entries (suffix minima of a block of 9, then a running
//!   prefix minimum over the next), streaming the circle rows from L1 instead of holding all 16.
//!
//! Results are bit-identical to the portable kernel; tests compare them.
//!
//! Unsafe code is confined to this module: the call into the `#[target_feature(enable =
//! "avx2")]` function, made only after `is_x86_feature_detected!("avx2")`, and unaligned
//! 32-byte loads and stores at offsets the row function checks against every slice's length
//! before its loop.
#![allow(unsafe_code)] // AVX2 intrinsics: every unsafe block says why it is sound

use std::arch::x86_64::{
    __m256i, _mm256_adds_epu8, _mm256_andnot_si256, _mm256_cmpeq_epi8, _mm256_loadu_si256,
    _mm256_max_epu8, _mm256_min_epu8, _mm256_movemask_epi8, _mm256_set1_epi8, _mm256_setzero_si256,
    _mm256_storeu_si256, _mm256_subs_epu8, _mm256_testz_si256,
};

/// Centres per vector.
pub(super) const LANES: usize = 32;

/// FAST-9 test and score of `n ≥ 32` centres of one row, as the portable `fast_row`: `ring[k]`
/// is the row of circle pixel `k` from its offset to the first centre, `centre` the row of
/// centres (each at least `n` long), `scores` at least `n` long and zero except where corners
/// are found. Returns `false` (and does nothing) without AVX2 or with too-short slices.
pub(super) fn fast_row(
    ring: &[&[u8]; 16],
    centre: &[u8],
    n: usize,
    t: u8,
    scores: &mut [u8],
    corners: &mut Vec<usize>,
) -> bool {
    if n < LANES
        || centre.len() < n
        || scores.len() < n
        || ring.iter().any(|r| r.len() < n)
        || !std::arch::is_x86_feature_detected!("avx2")
    {
        return false;
    }
    let ptrs: [*const u8; 16] = ring.map(|r| r.as_ptr());
    // SAFETY: AVX2 is available (checked above), and every slice holds at least `n` bytes, so
    // the loads and stores at `x..x + 32` for `x + 32 ≤ n` stay inside them.
    unsafe { fast_row_avx2(&ptrs, centre.as_ptr(), n, t, scores.as_mut_ptr(), corners) };
    true
}

/// # Safety
/// AVX2 must be available; `ring[k]`, `centre` and `scores` must be valid for `n ≥ 32` bytes.
#[target_feature(enable = "avx2")]
unsafe fn fast_row_avx2(
    ring: &[*const u8; 16],
    centre: *const u8,
    n: usize,
    t: u8,
    scores: *mut u8,
    corners: &mut Vec<usize>,
) {
    let mut x = 0;
    while x + LANES <= n {
        // SAFETY: x + 32 ≤ n (the caller's contract covers it).
        unsafe { fast_vector(ring, centre, x, x, t, scores, corners) };
        x += LANES;
    }
    if x < n {
        // The last vector overlaps its predecessor; lanes below `x` were done already.
        // SAFETY: n − 32 + 32 = n.
        unsafe { fast_vector(ring, centre, n - LANES, x, t, scores, corners) };
    }
}

/// Largest minimum of 9 circularly consecutive values of `e(j)`, `j` taken modulo 16, per lane:
/// suffix minima of `e0..e8`, a running minimum of `e9..` against them; then suffix minima of
/// `e9..e17` and a running minimum of `e18..e23`.
macro_rules! arc9 {
    ($e:ident) => {{
        let s8 = $e!(8);
        let s7 = _mm256_min_epu8($e!(7), s8);
        let s6 = _mm256_min_epu8($e!(6), s7);
        let s5 = _mm256_min_epu8($e!(5), s6);
        let s4 = _mm256_min_epu8($e!(4), s5);
        let s3 = _mm256_min_epu8($e!(3), s4);
        let s2 = _mm256_min_epu8($e!(2), s3);
        let s1 = _mm256_min_epu8($e!(1), s2);
        // Window 0: e0..e8.
        let mut best = _mm256_min_epu8($e!(0), s1);
        // Windows 1..=8: s_k with e9..e(k+8).
        let mut run = $e!(9);
        best = _mm256_max_epu8(best, _mm256_min_epu8(s1, run));
        run = _mm256_min_epu8(run, $e!(10));
        best = _mm256_max_epu8(best, _mm256_min_epu8(s2, run));
        run = _mm256_min_epu8(run, $e!(11));
        best = _mm256_max_epu8(best, _mm256_min_epu8(s3, run));
        run = _mm256_min_epu8(run, $e!(12));
        best = _mm256_max_epu8(best, _mm256_min_epu8(s4, run));
        run = _mm256_min_epu8(run, $e!(13));
        best = _mm256_max_epu8(best, _mm256_min_epu8(s5, run));
        run = _mm256_min_epu8(run, $e!(14));
        best = _mm256_max_epu8(best, _mm256_min_epu8(s6, run));
        run = _mm256_min_epu8(run, $e!(15));
        best = _mm256_max_epu8(best, _mm256_min_epu8(s7, run));
        run = _mm256_min_epu8(run, $e!(16));
        best = _mm256_max_epu8(best, _mm256_min_epu8(s8, run));
        // Suffix minima of e9..e17 (e16 = e0, e17 = e1).
        let u16_ = _mm256_min_epu8($e!(16), $e!(17));
        let u15 = _mm256_min_epu8($e!(15), u16_);
        let u14 = _mm256_min_epu8($e!(14), u15);
        let u13 = _mm256_min_epu8($e!(13), u14);
        let u12 = _mm256_min_epu8($e!(12), u13);
        let u11 = _mm256_min_epu8($e!(11), u12);
        let u10 = _mm256_min_epu8($e!(10), u11);
        // Window 9: e9..e17.
        best = _mm256_max_epu8(best, _mm256_min_epu8($e!(9), u10));
        // Windows 10..=15: u_k with e18..e(k+8).
        let mut run = $e!(18);
        best = _mm256_max_epu8(best, _mm256_min_epu8(u10, run));
        run = _mm256_min_epu8(run, $e!(19));
        best = _mm256_max_epu8(best, _mm256_min_epu8(u11, run));
        run = _mm256_min_epu8(run, $e!(20));
        best = _mm256_max_epu8(best, _mm256_min_epu8(u12, run));
        run = _mm256_min_epu8(run, $e!(21));
        best = _mm256_max_epu8(best, _mm256_min_epu8(u13, run));
        run = _mm256_min_epu8(run, $e!(22));
        best = _mm256_max_epu8(best, _mm256_min_epu8(u14, run));
        run = _mm256_min_epu8(run, $e!(23));
        best = _mm256_max_epu8(best, _mm256_min_epu8(u15, run));
        best
    }};
}

/// The 32 centres from column `x`: writes `scores[x..x + 32]` and pushes the corners at
/// `≥ from` when any lane is a corner.
///
/// # Safety
/// AVX2 must be available; `ring[k]`, `centre` and `scores` must be valid for `x + 32` bytes.
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn fast_vector(
    ring: &[*const u8; 16],
    centre: *const u8,
    x: usize,
    from: usize,
    t: u8,
    scores: *mut u8,
    corners: &mut Vec<usize>,
) {
    // SAFETY (every load below): `x + 32` bytes are valid from each pointer (the contract).
    macro_rules! load {
        ($p:expr) => {
            unsafe { _mm256_loadu_si256($p.add(x).cast::<__m256i>()) }
        };
    }
    let v = load!(centre);
    let tt = _mm256_set1_epi8(t as i8);
    let hi = _mm256_adds_epu8(v, tt);
    let lo = _mm256_subs_epu8(v, tt);
    let (c0, c4, c8, c12) = (
        load!(ring[0]),
        load!(ring[4]),
        load!(ring[8]),
        load!(ring[12]),
    );
    // An arc of 9 holds pixel 0 or 8, and pixel 4 or 12.
    let pass_bright = _mm256_min_epu8(
        _mm256_max_epu8(_mm256_subs_epu8(c0, hi), _mm256_subs_epu8(c8, hi)),
        _mm256_max_epu8(_mm256_subs_epu8(c4, hi), _mm256_subs_epu8(c12, hi)),
    );
    let pass_dark = _mm256_min_epu8(
        _mm256_max_epu8(_mm256_subs_epu8(lo, c0), _mm256_subs_epu8(lo, c8)),
        _mm256_max_epu8(_mm256_subs_epu8(lo, c4), _mm256_subs_epu8(lo, c12)),
    );
    let any_bright = _mm256_testz_si256(pass_bright, pass_bright) == 0;
    let any_dark = _mm256_testz_si256(pass_dark, pass_dark) == 0;
    if !any_bright && !any_dark {
        return;
    }
    let zero = _mm256_setzero_si256();
    let bright = if any_bright {
        macro_rules! e {
            ($j:expr) => {
                _mm256_subs_epu8(load!(ring[$j % 16]), v)
            };
        }
        arc9!(e)
    } else {
        zero
    };
    let dark = if any_dark {
        macro_rules! e {
            ($j:expr) => {
                _mm256_subs_epu8(v, load!(ring[$j % 16]))
            };
        }
        arc9!(e)
    } else {
        zero
    };
    let best = _mm256_max_epu8(bright, dark);
    // Corner ⇔ best > t ⇔ best ⊖ t ≠ 0; its score is best − 1.
    let not_corner = _mm256_cmpeq_epi8(_mm256_subs_epu8(best, tt), zero);
    let hits = !(_mm256_movemask_epi8(not_corner) as u32);
    if hits == 0 {
        return;
    }
    let score = _mm256_andnot_si256(not_corner, _mm256_subs_epu8(best, _mm256_set1_epi8(1)));
    // SAFETY: `scores` is valid for `x + 32` bytes (the contract).
    unsafe { _mm256_storeu_si256(scores.add(x).cast::<__m256i>(), score) };
    let skip = from - x;
    let mut mask = if skip >= LANES {
        0
    } else {
        hits & (u32::MAX << skip)
    };
    while mask != 0 {
        corners.push(x + mask.trailing_zeros() as usize);
        mask &= mask - 1;
    }
}
