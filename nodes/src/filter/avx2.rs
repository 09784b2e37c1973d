//! AVX2 kernels written with intrinsics where the auto-vectorizer does poorly: the 2×2 area
//! shrink of u8 images (pairs of adjacent pixels summed by `pmaddubsw` instead of
//! de-interleaving loads), and the u8 fixed-point smoothing filter (see [`super::gaussian`]),
//! built on one operation the auto-vectorizer cannot express:
//! the high half of a 16-bit product (`pmulhuw`). Written in portable Rust, `⌊a·b / 2¹⁶⌋`
//! is vectorized in 32-bit lanes (zero-extend, multiply, pack, permute), which costs twice the
//! instructions. The arithmetic here is exactly that of the portable kernels in `gaussian.rs`
//! (same products, same truncations, same order of wrapping 16-bit additions), so results are
//! bit-identical with or without AVX2; tests compare the two.
//!
//! The high multiply itself is one `vpmulhuw` in inline assembly: LLVM rewrites the
//! `_mm256_mulhi_epu16` intrinsic into generic IR and, when an operand is an average or a
//! shifted value, lowers it back in 32-bit lanes again.
//!
//! Both compute exactly what the portable code computes (integer arithmetic), so results are
//! bit-identical with or without AVX2.
//!
//! Unsafe code is confined to this module: the calls into `#[target_feature(enable = "avx2")]`
//! functions, made only after `is_x86_feature_detected!("avx2")`, unaligned loads and stores
//! through pointers to fixed-size arrays borrowed from slices, and that one instruction.
#![allow(unsafe_code)] // AVX2 intrinsics: every unsafe block says why it is sound

use std::arch::x86_64::{
    __m128i, __m256i, _mm_loadu_si128, _mm_setzero_si128, _mm_storel_epi64, _mm_storeu_si128,
    _mm256_add_epi16, _mm256_castsi256_si128, _mm256_cvtepu8_epi16, _mm256_extracti128_si256,
    _mm256_loadu_si256, _mm256_maddubs_epi16, _mm256_packus_epi16, _mm256_permute4x64_epi64,
    _mm256_permutevar8x32_epi32, _mm256_set_m128i, _mm256_set1_epi8, _mm256_set1_epi16,
    _mm256_setr_epi8, _mm256_setr_epi32, _mm256_shuffle_epi8, _mm256_slli_epi16,
    _mm256_srli_epi16 as srli16, _mm256_srli_epi16, _mm256_storeu_si256,
};

/// Lanes per vector (16-bit).
const LANES: usize = 16;

/// Whether the running CPU has AVX2 (cached by the standard library).
pub(crate) fn available() -> bool {
    std::arch::is_x86_feature_detected!("avx2")
}

/// Column pass from the `2h + 1` u8 rows `rows` (top first, `h = pairs.len()`):
/// `out[i] = bias + ⌊256·c[i] · centre / 2¹⁶⌋ + Σ_j ⌊128·(rows[j][i] + rows[2h−j][i]) ·
/// pairs[j] / 2¹⁶⌋` for the whole vectors of `out`; returns how many samples it wrote (a
/// multiple of 16; the caller finishes the tail). `None` without AVX2.
pub(crate) fn column_u8(
    rows: &[&[u8]],
    pairs: &[u16],
    centre_weight: u16,
    bias: u16,
    out: &mut [u16],
) -> Option<usize> {
    if !available() {
        return None;
    }
    // SAFETY: AVX2 is available (checked above).
    Some(unsafe { column_u8_avx2(rows, pairs, centre_weight, bias, out) })
}

#[target_feature(enable = "avx2")]
fn column_u8_avx2(
    rows: &[&[u8]],
    pairs: &[u16],
    centre_weight: u16,
    bias: u16,
    out: &mut [u16],
) -> usize {
    match pairs.len() {
        1 => column_u8_taps::<1>(rows, pairs, centre_weight, bias, out),
        2 => column_u8_taps::<2>(rows, pairs, centre_weight, bias, out),
        3 => column_u8_taps::<3>(rows, pairs, centre_weight, bias, out),
        4 => column_u8_taps::<4>(rows, pairs, centre_weight, bias, out),
        5 => column_u8_taps::<5>(rows, pairs, centre_weight, bias, out),
        6 => column_u8_taps::<6>(rows, pairs, centre_weight, bias, out),
        7 => column_u8_taps::<7>(rows, pairs, centre_weight, bias, out),
        _ => 0,
    }
}

/// [`column_u8_avx2`] for `2H + 1` taps.
#[target_feature(enable = "avx2")]
fn column_u8_taps<const H: usize>(
    rows: &[&[u8]],
    pairs: &[u16],
    centre_weight: u16,
    bias: u16,
    out: &mut [u16],
) -> usize {
    let (Ok(pairs), true) = (<[u16; H]>::try_from(pairs), rows.len() == 2 * H + 1) else {
        return 0;
    };
    let n = rows.iter().fold(out.len(), |n, row| n.min(row.len()));
    let whole = n - n % LANES;
    let Some(centre) = rows.get(H).and_then(|r| r.get(..whole)) else {
        return 0;
    };
    let tap = |k: usize| rows.get(k).and_then(|r| r.get(..whole)).unwrap_or(&[]);
    let left: [&[u8]; H] = std::array::from_fn(tap);
    let right: [&[u8]; H] = std::array::from_fn(|j| tap(2 * H - j));
    let bias = _mm256_set1_epi16(bias as i16);
    let centre_weight = _mm256_set1_epi16(centre_weight as i16);
    let weights: [__m256i; H] = std::array::from_fn(|j| _mm256_set1_epi16(pairs[j] as i16));
    for (k, o) in out[..whole].chunks_exact_mut(LANES).enumerate() {
        let i = k * LANES;
        let c = _mm256_slli_epi16::<8>(widen(centre, i));
        let mut acc = _mm256_add_epi16(bias, mulhi(c, centre_weight));
        for j in 0..H {
            let sum = _mm256_add_epi16(widen(left[j], i), widen(right[j], i));
            acc = _mm256_add_epi16(acc, mulhi(_mm256_slli_epi16::<7>(sum), weights[j]));
        }
        store16(o, acc);
    }
    whole
}

/// Row pass to u8: `out[i] = (bias + ⌊p_c · centre / 2¹⁶⌋ + Σ_j ⌊avg(p_l, p_r) · pairs[j] /
/// 2¹⁶⌋) >> 8` where `p_k = padded[offsets[k] + i]` and `avg` rounds up; whole vectors of 32
/// outputs only, returns how many it wrote. `None` without AVX2.
pub(crate) fn row_to_u8(
    padded: &[u16],
    offsets: &[usize],
    pairs: &[u16],
    centre_weight: u16,
    bias: u16,
    out: &mut [u8],
) -> Option<usize> {
    if !available() {
        return None;
    }
    // SAFETY: AVX2 is available (checked above).
    Some(unsafe { row_to_u8_avx2(padded, offsets, pairs, centre_weight, bias, out) })
}

#[target_feature(enable = "avx2")]
fn row_to_u8_avx2(
    padded: &[u16],
    offsets: &[usize],
    pairs: &[u16],
    centre_weight: u16,
    bias: u16,
    out: &mut [u8],
) -> usize {
    match pairs.len() {
        1 => row_to_u8_taps::<1>(padded, offsets, pairs, centre_weight, bias, out),
        2 => row_to_u8_taps::<2>(padded, offsets, pairs, centre_weight, bias, out),
        3 => row_to_u8_taps::<3>(padded, offsets, pairs, centre_weight, bias, out),
        4 => row_to_u8_taps::<4>(padded, offsets, pairs, centre_weight, bias, out),
        5 => row_to_u8_taps::<5>(padded, offsets, pairs, centre_weight, bias, out),
        6 => row_to_u8_taps::<6>(padded, offsets, pairs, centre_weight, bias, out),
        7 => row_to_u8_taps::<7>(padded, offsets, pairs, centre_weight, bias, out),
        _ => 0,
    }
}

/// [`row_to_u8_avx2`] for `2H + 1` taps.
#[target_feature(enable = "avx2")]
fn row_to_u8_taps<const H: usize>(
    padded: &[u16],
    offsets: &[usize],
    pairs: &[u16],
    centre_weight: u16,
    bias: u16,
    out: &mut [u8],
) -> usize {
    let (Ok(pairs), Some(offsets)) = (<[u16; H]>::try_from(pairs), offsets.get(..2 * H + 1)) else {
        return 0;
    };
    // Every tap reads `offsets[k] + i` for i < n.
    let reach = offsets.iter().copied().max().unwrap_or(0);
    let n = out.len().min(padded.len().saturating_sub(reach));
    let whole = n - n % (2 * LANES);
    let tap = |k: usize| {
        offsets
            .get(k)
            .and_then(|&o| padded.get(o..o + whole))
            .unwrap_or(&[])
    };
    let left: [&[u16]; H] = std::array::from_fn(tap);
    let right: [&[u16]; H] = std::array::from_fn(|j| tap(2 * H - j));
    let centre = tap(H);
    let bias = _mm256_set1_epi16(bias as i16);
    let centre_weight = _mm256_set1_epi16(centre_weight as i16);
    let weights: [__m256i; H] = std::array::from_fn(|j| _mm256_set1_epi16(pairs[j] as i16));
    let filter = |i: usize| {
        let mut acc = _mm256_add_epi16(bias, mulhi(load16(centre, i), centre_weight));
        for j in 0..H {
            let pair = avg(load16(left[j], i), load16(right[j], i));
            acc = _mm256_add_epi16(acc, mulhi(pair, weights[j]));
        }
        _mm256_srli_epi16::<8>(acc)
    };
    for (k, o) in out[..whole].chunks_exact_mut(2 * LANES).enumerate() {
        let i = k * 2 * LANES;
        let low = filter(i);
        let high = filter(i + LANES);
        // packus interleaves the 128-bit halves; the permute puts the 32 bytes in order.
        let bytes = _mm256_permute4x64_epi64::<0b11_01_10_00>(_mm256_packus_epi16(low, high));
        store32(o, bytes);
    }
    whole
}

/// `⌈(a + b) / 2⌉` in each unsigned 16-bit lane (`vpavgw`, in assembly for the same reason as
/// [`mulhi`]).
#[target_feature(enable = "avx2")]
fn avg(a: __m256i, b: __m256i) -> __m256i {
    let out: __m256i;
    // SAFETY: one register-to-register AVX2 instruction (available: this function requires
    // it); no memory, stack or flags are touched.
    unsafe {
        std::arch::asm!(
            "vpavgw {out}, {a}, {b}",
            a = in(ymm_reg) a,
            b = in(ymm_reg) b,
            out = lateout(ymm_reg) out,
            options(pure, nomem, nostack, preserves_flags),
        );
    }
    out
}

/// `⌊a·b / 2¹⁶⌋` in each unsigned 16-bit lane.
#[target_feature(enable = "avx2")]
fn mulhi(a: __m256i, b: __m256i) -> __m256i {
    let out: __m256i;
    // SAFETY: one register-to-register AVX2 instruction (available: this function requires
    // it); no memory, stack or flags are touched.
    unsafe {
        std::arch::asm!(
            "vpmulhuw {out}, {a}, {b}",
            a = in(ymm_reg) a,
            b = in(ymm_reg) b,
            out = lateout(ymm_reg) out,
            options(pure, nomem, nostack, preserves_flags),
        );
    }
    out
}

/// 16 u8 samples from `row[i..]`, zero-extended to 16-bit lanes (zeros past the end).
#[target_feature(enable = "avx2")]
fn widen(row: &[u8], i: usize) -> __m256i {
    match row
        .get(i..i + LANES)
        .and_then(|s| <&[u8; LANES]>::try_from(s).ok())
    {
        // SAFETY: `bytes` is 16 readable bytes; the load has no alignment requirement.
        Some(bytes) => {
            _mm256_cvtepu8_epi16(unsafe { _mm_loadu_si128(bytes.as_ptr().cast::<__m128i>()) })
        }
        None => _mm256_set1_epi16(0),
    }
}

/// 16 u16 samples from `data[i..]` (zeros past the end).
#[target_feature(enable = "avx2")]
fn load16(data: &[u16], i: usize) -> __m256i {
    match data
        .get(i..i + LANES)
        .and_then(|s| <&[u16; LANES]>::try_from(s).ok())
    {
        // SAFETY: `lanes` is 32 readable bytes; the load has no alignment requirement.
        Some(lanes) => unsafe { _mm256_loadu_si256(lanes.as_ptr().cast::<__m256i>()) },
        None => _mm256_set1_epi16(0),
    }
}

/// Stores 16 u16 lanes into `out` (nothing unless it holds exactly 16).
#[target_feature(enable = "avx2")]
fn store16(out: &mut [u16], v: __m256i) {
    if let Ok(lanes) = <&mut [u16; LANES]>::try_from(out) {
        // SAFETY: `lanes` is 32 writable bytes, exclusively borrowed; unaligned store.
        unsafe { _mm256_storeu_si256(lanes.as_mut_ptr().cast::<__m256i>(), v) }
    }
}

/// Stores 32 u8 lanes into `out` (nothing unless it holds exactly 32).
#[target_feature(enable = "avx2")]
fn store32(out: &mut [u8], v: __m256i) {
    if let Ok(bytes) = <&mut [u8; 32]>::try_from(out) {
        // SAFETY: `bytes` is 32 writable bytes, exclusively borrowed; unaligned store.
        unsafe { _mm256_storeu_si256(bytes.as_mut_ptr().cast::<__m256i>(), v) }
    }
}

/// 2×2 block means of a u8 image with `channels` 1, 3 or 4, `(a + b + c + d + 2) >> 2`, for
/// the whole steps of 32 output samples (24 for RGB) of `out` from source rows `top` and
/// `bottom` (each at least `2·out.len()` samples); returns how many samples it wrote. `None`
/// without AVX2 or for other channel counts.
pub(crate) fn half_u8(channels: usize, top: &[u8], bottom: &[u8], out: &mut [u8]) -> Option<usize> {
    if !available() {
        return None;
    }
    match channels {
        // SAFETY: AVX2 is available (checked above).
        1 | 4 => Some(unsafe { half_u8_avx2(channels == 4, top, bottom, out) }),
        // SAFETY: as above.
        3 => Some(unsafe { half_rgb_avx2(top, bottom, out) }),
        _ => None,
    }
}

/// 2×2 means of RGB u8 rows, 24 output bytes (8 pixels) per step from 48 source bytes per row.
///
/// Each 128-bit lane takes 4 source pixels (12 bytes): a byte shuffle puts the same channel of
/// the two pixels of a pair side by side, `pmaddubsw` sums each pair, and the lanes of the two
/// registers are arranged so that packing, one more shuffle and a dword permute leave the 24
/// means in order. Source offsets per step: lanes at +0 and +24 (register `a`), +8 and +32
/// (register `b`, whose lanes use bytes 4..16), so no load reaches past the 48 bytes.
#[target_feature(enable = "avx2")]
fn half_rgb_avx2(top: &[u8], bottom: &[u8], out: &mut [u8]) -> usize {
    const Z: i8 = -128; // shuffle index that writes zero
    let n = out.len().min(top.len() / 2).min(bottom.len() / 2);
    let whole = n - n % 24;
    let ones = _mm256_set1_epi8(1);
    let two = _mm256_set1_epi16(2);
    let pair_a = _mm256_setr_epi8(
        0, 3, 1, 4, 2, 5, 6, 9, 7, 10, 8, 11, Z, Z, Z, Z, 0, 3, 1, 4, 2, 5, 6, 9, 7, 10, 8, 11, Z,
        Z, Z, Z,
    );
    let pair_b = _mm256_setr_epi8(
        4, 7, 5, 8, 6, 9, 10, 13, 11, 14, 12, 15, Z, Z, Z, Z, 4, 7, 5, 8, 6, 9, 10, 13, 11, 14, 12,
        15, Z, Z, Z, Z,
    );
    let compact = _mm256_setr_epi8(
        0, 1, 2, 3, 4, 5, 8, 9, 10, 11, 12, 13, Z, Z, Z, Z, 0, 1, 2, 3, 4, 5, 8, 9, 10, 11, 12, 13,
        Z, Z, Z, Z,
    );
    let gather = _mm256_setr_epi32(0, 1, 2, 4, 5, 6, 3, 7);
    // Pair sums (u16) of the lanes at `i + lo` and `i + hi`, shuffled by `order`.
    let pairs = |row: &[u8], i: usize, lo: usize, hi: usize, order: __m256i| {
        let v = _mm256_set_m128i(load_bytes16(row, i + hi), load_bytes16(row, i + lo));
        _mm256_maddubs_epi16(_mm256_shuffle_epi8(v, order), ones)
    };
    for (k, o) in out[..whole].chunks_exact_mut(24).enumerate() {
        let i = 48 * k;
        let a = _mm256_add_epi16(
            pairs(top, i, 0, 24, pair_a),
            pairs(bottom, i, 0, 24, pair_a),
        );
        let b = _mm256_add_epi16(
            pairs(top, i, 8, 32, pair_b),
            pairs(bottom, i, 8, 32, pair_b),
        );
        let (a, b) = (
            srli16::<2>(_mm256_add_epi16(a, two)),
            srli16::<2>(_mm256_add_epi16(b, two)),
        );
        let means = _mm256_shuffle_epi8(_mm256_packus_epi16(a, b), compact);
        let means = _mm256_permutevar8x32_epi32(means, gather);
        store24(o, means);
    }
    whole
}

/// 16 bytes from `data[i..]` (zeros past the end).
#[target_feature(enable = "avx2")]
fn load_bytes16(data: &[u8], i: usize) -> __m128i {
    match data
        .get(i..i + 16)
        .and_then(|s| <&[u8; 16]>::try_from(s).ok())
    {
        // SAFETY: `bytes` is 16 readable bytes; the load has no alignment requirement.
        Some(bytes) => unsafe { _mm_loadu_si128(bytes.as_ptr().cast::<__m128i>()) },
        None => _mm_setzero_si128(),
    }
}

/// Stores the low 24 bytes of `v` into `out` (nothing unless it holds exactly 24).
#[target_feature(enable = "avx2")]
fn store24(out: &mut [u8], v: __m256i) {
    if let Ok(bytes) = <&mut [u8; 24]>::try_from(out) {
        let (low, high) = bytes.split_at_mut(16);
        // SAFETY: `low` is 16 and `high` 8 writable bytes, exclusively borrowed; unaligned
        // stores of 16 and 8 bytes.
        unsafe {
            _mm_storeu_si128(
                low.as_mut_ptr().cast::<__m128i>(),
                _mm256_castsi256_si128(v),
            );
            _mm_storel_epi64(
                high.as_mut_ptr().cast::<__m128i>(),
                _mm256_extracti128_si256::<1>(v),
            );
        }
    }
}

#[target_feature(enable = "avx2")]
fn half_u8_avx2(rgba: bool, top: &[u8], bottom: &[u8], out: &mut [u8]) -> usize {
    let n = out.len().min(top.len() / 2).min(bottom.len() / 2);
    let whole = n - n % 32;
    let ones = _mm256_set1_epi8(1);
    let two = _mm256_set1_epi16(2);
    // RGBA: within each 8 bytes (two pixels), put the same channel of both pixels side by side.
    let order = _mm256_setr_epi8(
        0, 4, 1, 5, 2, 6, 3, 7, 8, 12, 9, 13, 10, 14, 11, 15, 0, 4, 1, 5, 2, 6, 3, 7, 8, 12, 9, 13,
        10, 14, 11, 15,
    );
    // Pair sums (u16) of 32 source bytes from `i`.
    let pairs = |row: &[u8], i: usize| {
        let v = load_bytes32(row, i);
        let v = if rgba {
            _mm256_shuffle_epi8(v, order)
        } else {
            v
        };
        _mm256_maddubs_epi16(v, ones)
    };
    for (k, o) in out[..whole].chunks_exact_mut(32).enumerate() {
        let i = 2 * 32 * k;
        let low = _mm256_add_epi16(_mm256_add_epi16(pairs(top, i), pairs(bottom, i)), two);
        let high = _mm256_add_epi16(
            _mm256_add_epi16(pairs(top, i + 32), pairs(bottom, i + 32)),
            two,
        );
        let (low, high) = (srli16::<2>(low), srli16::<2>(high));
        let bytes = _mm256_permute4x64_epi64::<0b11_01_10_00>(_mm256_packus_epi16(low, high));
        store32(o, bytes);
    }
    whole
}

/// 32 bytes from `data[i..]` (zeros past the end).
#[target_feature(enable = "avx2")]
fn load_bytes32(data: &[u8], i: usize) -> __m256i {
    match data
        .get(i..i + 32)
        .and_then(|s| <&[u8; 32]>::try_from(s).ok())
    {
        // SAFETY: `bytes` is 32 readable bytes; the load has no alignment requirement.
        Some(bytes) => unsafe { _mm256_loadu_si256(bytes.as_ptr().cast::<__m256i>()) },
        None => _mm256_set1_epi16(0),
    }
}

/// One group of 8 outputs of a one-channel linear horizontal pass whose 8 sample pairs lie in
/// the 16 bytes from `base`: `shuffle` puts pair `i` (bytes `r_i`, `r_i + 1` after `base`) at
/// bytes `2i`, `2i + 1`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct PairGroup {
    pub base: u32,
    pub shuffle: [u8; 16],
}

/// The groups of 8 outputs from the start of a row whose pairs (`starts`, non-decreasing, each
/// `≤ src − 2`) fit 16 bytes that lie inside a source row of `src` samples; stops at the
/// first group that does not.
pub(crate) fn pair_groups(starts: &[u32], src: usize) -> Vec<PairGroup> {
    let mut groups = Vec::new();
    for chunk in starts.chunks_exact(8) {
        let base = chunk[0];
        if base as usize + 16 > src {
            break;
        }
        let mut shuffle = [0u8; 16];
        let mut fits = true;
        for (i, &s) in chunk.iter().enumerate() {
            match s.checked_sub(base) {
                Some(r) if r <= 14 => {
                    shuffle[2 * i] = r as u8;
                    shuffle[2 * i + 1] = r as u8 + 1;
                }
                _ => fits = false,
            }
        }
        if !fits {
            break;
        }
        groups.push(PairGroup { base, shuffle });
    }
    groups
}

/// `out[o] = (row[s]·w₀ + row[s + 1]·w₁) ≫ 4` (32-bit sum, as the portable pass) for the 8
/// outputs of each group, from the start of `out`; returns how many outputs it wrote. `None`
/// without AVX2.
pub(crate) fn h_pairs_u8(
    row: &[u8],
    groups: &[PairGroup],
    weights: &[[i16; 2]],
    out: &mut [i16],
) -> Option<usize> {
    if !available() {
        return None;
    }
    // SAFETY: AVX2 is available (checked above).
    Some(unsafe { h_pairs_u8_avx2(row, groups, weights, out) })
}

#[target_feature(enable = "avx2")]
fn h_pairs_u8_avx2(
    row: &[u8],
    groups: &[PairGroup],
    weights: &[[i16; 2]],
    out: &mut [i16],
) -> usize {
    use std::arch::x86_64::{
        _mm_shuffle_epi8, _mm256_madd_epi16, _mm256_packs_epi32, _mm256_srai_epi32,
    };
    let mut done = 0;
    for ((group, w), o) in groups
        .iter()
        .zip(weights.chunks_exact(8))
        .zip(out.chunks_exact_mut(8))
    {
        let source = load_bytes16(row, group.base as usize);
        // SAFETY: `shuffle` is 16 readable bytes; unaligned load.
        let mask = unsafe { _mm_loadu_si128(group.shuffle.as_ptr().cast::<__m128i>()) };
        let pairs = _mm256_cvtepu8_epi16(_mm_shuffle_epi8(source, mask));
        let Ok(w) = <&[[i16; 2]; 8]>::try_from(w) else {
            break;
        };
        // SAFETY: `w` is 8 pairs of i16, 32 readable bytes; unaligned load.
        let w = unsafe { _mm256_loadu_si256(w.as_ptr().cast::<__m256i>()) };
        let sums = _mm256_srai_epi32(_mm256_madd_epi16(pairs, w), 4);
        // Lane 0 holds sums 0..3 twice, lane 1 sums 4..7: take the low quarter of each.
        let packed = _mm256_permute4x64_epi64(_mm256_packs_epi32(sums, sums), 0b10_00);
        let Ok(o) = <&mut [i16; 8]>::try_from(o) else {
            break;
        };
        // SAFETY: `o` is 16 writable bytes, exclusively borrowed; unaligned store.
        unsafe {
            _mm_storeu_si128(
                o.as_mut_ptr().cast::<__m128i>(),
                _mm256_castsi256_si128(packed),
            )
        };
        done += 8;
    }
    done
}
