//! AVX2 + FMA preselection kernel of the float brute-force matcher (see
//! [`super::brute_force`]): the approximate squared distances `‖q‖² + ‖t‖² − 2 q·t` of four
//! query rows against a block of train rows, as a small matrix product.
//!
//! The train rows are packed in panels of eight ([`Panels`]): element `k` of the panel's eight
//! rows is one 8-lane vector, so one broadcast query element times one panel vector updates
//! eight dot products at once, and no horizontal reduction is needed. Four queries × two panels
//! are eight accumulators in registers; per element that is six loads (two panel vectors, four
//! broadcasts) for eight fused multiply–adds.
//!
//! Each dot product is a plain running sum over the elements (one FMA each), a different order
//! and rounding than the portable kernel's eight lanes. Both stay within the rounding bound the
//! matcher allows for (at most one unit roundoff per element and per final addition), and
//! every candidate within twice that bound of the second-nearest is re-measured exactly, so the
//! matcher's results are identical with either kernel; tests compare them.
//!
//! Unsafe code is confined to this module: the call into the `#[target_feature(enable =
//! "avx2,fma")]` function, made only after `is_x86_feature_detected!` confirmed both, and
//! unaligned loads and stores at offsets checked against every slice's length before the loops.
#![allow(unsafe_code)] // AVX2 intrinsics: every unsafe block says why it is sound

use std::arch::x86_64::{
    __m256, _mm256_add_ps, _mm256_broadcast_ss, _mm256_fmadd_ps, _mm256_fnmadd_ps, _mm256_loadu_ps,
    _mm256_set1_ps, _mm256_setzero_ps, _mm256_storeu_ps,
};

/// Rows per panel (one 8-lane vector).
pub(super) const PANEL: usize = 8;

/// Queries per kernel call.
pub(super) const QUERIES: usize = 4;

/// Train rows packed in panels of [`PANEL`] rows: element `k` of row `8p + r` is at
/// `(p · dim + k) · 8 + r`; rows past the last are zero. `norms` holds each row's squared norm,
/// zero-padded to whole panels.
pub(super) struct Panels {
    data: Vec<f32>,
    norms: Vec<f32>,
    dim: usize,
    rows: usize,
}

impl Panels {
    /// Packs the `dim`-element rows of `t`; `norms[j]` is row `j`'s squared norm.
    pub(super) fn new(t: &[f32], dim: usize, norms: &[f32]) -> Panels {
        let rows = t.len().checked_div(dim).unwrap_or(0);
        let panels = rows.div_ceil(PANEL);
        let mut data = vec![0.0f32; panels * dim * PANEL];
        for (j, row) in t.chunks_exact(dim.max(1)).enumerate() {
            let base = (j / PANEL) * dim * PANEL + j % PANEL;
            for (k, &v) in row.iter().enumerate() {
                data[base + k * PANEL] = v;
            }
        }
        let mut padded = vec![0.0f32; panels * PANEL];
        for (dst, &n) in padded.iter_mut().zip(norms.iter().take(rows)) {
            *dst = n;
        }
        Panels {
            data,
            norms: padded,
            dim,
            rows,
        }
    }
}

/// Whether this CPU runs the kernel.
pub(super) fn available() -> bool {
    is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma")
}

/// Approximate squared distances of the [`QUERIES`] rows of `q` (row `i` at `i · stride_q`,
/// its first `dim` elements used) with squared norms `qnorm`, against train rows `t0..t1` of
/// `panels` (`t0` a multiple of [`PANEL`]), into `out[i · stride + j]`. Returns `false` (and
/// writes nothing) without AVX2 and FMA or when a slice is too short.
#[allow(clippy::too_many_arguments)]
pub(super) fn approx_block(
    q: &[f32],
    stride_q: usize,
    qnorm: &[f32],
    panels: &Panels,
    out: &mut [f32],
    stride: usize,
    t0: usize,
    t1: usize,
) -> bool {
    let dim = panels.dim;
    let fits = t0.is_multiple_of(PANEL)
        && t0 <= t1
        && t1 <= panels.rows
        && t1 <= stride
        && stride_q >= dim
        && q.len() >= (QUERIES - 1) * stride_q + dim
        && qnorm.len() >= QUERIES
        && out.len() >= (QUERIES - 1) * stride + t1;
    if !fits || !available() {
        return false;
    }
    // SAFETY: AVX2 and FMA were detected above; the bounds checked above are the ones
    // `approx_block_avx2` documents.
    unsafe { approx_block_avx2(q, stride_q, qnorm, panels, out, stride, t0, t1) };
    true
}

/// See [`approx_block`]. Requires: AVX2 and FMA; `t0 % 8 == 0`, `t0 ≤ t1 ≤ panels.rows`,
/// `t1 ≤ stride`, `stride_q ≥ dim`, `q.len() ≥ 3 · stride_q + dim`, `qnorm.len() ≥ 4`,
/// `out.len() ≥ 3 · stride + t1`.
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2,fma")]
unsafe fn approx_block_avx2(
    q: &[f32],
    stride_q: usize,
    qnorm: &[f32],
    panels: &Panels,
    out: &mut [f32],
    stride: usize,
    t0: usize,
    t1: usize,
) {
    let dim = panels.dim;
    let two = _mm256_set1_ps(2.0);
    let qn: [__m256; QUERIES] = std::array::from_fn(|i| _mm256_set1_ps(qnorm[i]));
    // `q` holds row i's first dim elements at i · stride_q (checked by the caller).
    let rows: [&[f32]; QUERIES] = std::array::from_fn(|i| &q[i * stride_q..i * stride_q + dim]);
    let mut j = t0;
    while j < t1 {
        // Two panels while at least nine rows remain, else one.
        let pair = t1 - j > PANEL;
        let p = j / PANEL;
        // Panel p (and p + 1 when `pair`) lie inside `panels.data`: p < ⌈rows / 8⌉ because
        // j < t1 ≤ rows, and p + 1 < ⌈rows / 8⌉ because j + 8 < t1 ≤ rows.
        let a_ptr = panels.data[p * dim * PANEL..].as_ptr();
        let b_ptr = if pair {
            panels.data[(p + 1) * dim * PANEL..].as_ptr()
        } else {
            a_ptr
        };
        let mut acc = [[_mm256_setzero_ps(); 2]; QUERIES];
        for k in 0..dim {
            // SAFETY: element k < dim of a panel is the 8 floats at k · 8 from its start, inside
            // the panel's dim · 8 floats (see above).
            let (va, vb) = unsafe {
                (
                    _mm256_loadu_ps(a_ptr.add(k * PANEL)),
                    _mm256_loadu_ps(b_ptr.add(k * PANEL)),
                )
            };
            for (row, query) in acc.iter_mut().zip(&rows) {
                let x = _mm256_broadcast_ss(&query[k]);
                row[0] = _mm256_fmadd_ps(x, va, row[0]);
                row[1] = _mm256_fmadd_ps(x, vb, row[1]);
            }
        }
        let panels_here = if pair { 2 } else { 1 };
        for (i, row) in acc.iter().enumerate() {
            for (h, &dot) in row.iter().enumerate().take(panels_here) {
                let col = j + h * PANEL;
                // `norms` has ⌈rows / 8⌉ · 8 entries and col is a panel start below rows.
                // SAFETY: col + 8 ≤ norms.len() (col is the start of an existing panel).
                let tn = unsafe { _mm256_loadu_ps(panels.norms[col..col + PANEL].as_ptr()) };
                let d = _mm256_fnmadd_ps(two, dot, _mm256_add_ps(qn[i], tn));
                let valid = (t1 - col).min(PANEL);
                let start = i * stride + col;
                if valid == PANEL {
                    // SAFETY: out[start..start + 8] is in bounds: col + 8 ≤ t1 and
                    // out.len() ≥ 3 · stride + t1 ≥ i · stride + t1.
                    unsafe { _mm256_storeu_ps(out[start..start + PANEL].as_mut_ptr(), d) };
                } else {
                    let mut tmp = [0.0f32; PANEL];
                    // SAFETY: `tmp` holds 8 floats.
                    unsafe { _mm256_storeu_ps(tmp.as_mut_ptr(), d) };
                    out[start..start + valid].copy_from_slice(&tmp[..valid]);
                }
            }
        }
        j += panels_here * PANEL;
    }
}
