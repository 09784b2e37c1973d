//! One 8×8 block: orthonormal DCT-II in f64, quantization, zig-zag scan, run-length
//! (run, level) pairs with an end-of-block, and their Exp-Golomb coding.
//!
//! Entropy code of a block from scan position `start` (1 for intra blocks, whose DC is coded
//! apart; 0 for inter residuals): for each nonzero level in zig-zag order, `ue(run + 1)`
//! (run = zeros skipped since the previous nonzero), `ue(|level| − 1)` and one sign bit
//! (1 = negative); then the end-of-block `ue(0)`, always, even after position 63.

use crate::filter::frequency::dct::dct_matrix_f64;

use super::bits::{BitReader, BitWriter};

/// Coefficients per block.
pub const N: usize = 64;

/// Largest quantized level magnitude written or accepted.
pub const MAX_LEVEL: i32 = 1 << 20;

/// JPEG's example luminance quantization table (ITU-T T.81 Annex K, Table K.1), raster order.
#[rustfmt::skip]
pub const JPEG_LUMA: [u16; N] = [
    16, 11, 10, 16, 24, 40, 51, 61,
    12, 12, 14, 19, 26, 58, 60, 55,
    14, 13, 16, 24, 40, 57, 69, 56,
    14, 17, 22, 29, 51, 87, 80, 62,
    18, 22, 37, 56, 68, 109, 103, 77,
    24, 35, 55, 64, 81, 104, 113, 92,
    49, 64, 78, 87, 103, 121, 120, 101,
    72, 92, 95, 98, 112, 100, 103, 99,
];

/// Zig-zag scan order: `zigzag_order()[i]` is the raster index of the `i`-th coefficient in
/// scan order (JPEG's order, T.81 Figure A.6), built by walking the anti-diagonals.
pub fn zigzag_order() -> [usize; N] {
    let mut order = [0usize; N];
    let mut i = 0;
    for s in 0..15usize {
        // Anti-diagonal s: row + col = s. Even s runs bottom-left → top-right (row falling).
        let lo = s.saturating_sub(7);
        let hi = s.min(7);
        for k in lo..=hi {
            let row = if s % 2 == 0 { hi - (k - lo) } else { k };
            order[i] = row * 8 + (s - row);
            i += 1;
        }
    }
    order
}

/// Transform, quantizer steps and scan shared by the encoder and the decoder.
#[derive(Debug, Clone)]
pub struct BlockCoder {
    c: [[f64; 8]; 8],
    /// Quantizer step per coefficient, raster order.
    steps: [f64; N],
    zigzag: [usize; N],
}

impl BlockCoder {
    /// A coder whose step for coefficient `i` is `quantizer · matrix[i] / 16` (`matrix` =
    /// [`JPEG_LUMA`], or 16 everywhere when `flat`), so `quantizer` is the flat-matrix step.
    pub fn new(quantizer: f64, flat: bool) -> BlockCoder {
        let mut steps = [0.0; N];
        for (s, &m) in steps.iter_mut().zip(&JPEG_LUMA) {
            let m = if flat { 16.0 } else { f64::from(m) };
            *s = quantizer * m / 16.0;
        }
        BlockCoder {
            c: dct_matrix_f64(),
            steps,
            zigzag: zigzag_order(),
        }
    }

    /// Orthonormal 2-D DCT-II `C·X·Cᵀ` of a raster 8×8 block (`inverse`: `Cᵀ·Y·C`).
    pub fn transform(&self, x: &[f64; N], inverse: bool) -> [f64; N] {
        let c = &self.c;
        let at = |k: usize, n: usize| if inverse { c[n][k] } else { c[k][n] };
        // tmp = X·Mᵀ, out = M·tmp with M = C or Cᵀ.
        let mut tmp = [0.0; N];
        for r in 0..8 {
            for k in 0..8 {
                let mut s = 0.0;
                for n in 0..8 {
                    s += x[r * 8 + n] * at(k, n);
                }
                tmp[r * 8 + k] = s;
            }
        }
        let mut out = [0.0; N];
        for k in 0..8 {
            for col in 0..8 {
                let mut s = 0.0;
                for r in 0..8 {
                    s += at(k, r) * tmp[r * 8 + col];
                }
                out[k * 8 + col] = s;
            }
        }
        out
    }

    /// Quantized levels (raster) of the DCT of `samples`: `round(coef / step)`, ties away
    /// from zero, clamped to ±[`MAX_LEVEL`].
    pub fn quantize(&self, samples: &[f64; N]) -> [i32; N] {
        let coef = self.transform(samples, false);
        let mut levels = [0i32; N];
        for ((l, &c), &s) in levels.iter_mut().zip(&coef).zip(&self.steps) {
            *l = (c / s)
                .round()
                .clamp(-f64::from(MAX_LEVEL), f64::from(MAX_LEVEL)) as i32;
        }
        levels
    }

    /// Reconstructed samples `prediction + IDCT(level · step)`, rounded and clamped to u8.
    pub fn reconstruct(&self, levels: &[i32; N], prediction: &[f64; N]) -> [u8; N] {
        let mut coef = [0.0; N];
        for ((c, &l), &s) in coef.iter_mut().zip(levels).zip(&self.steps) {
            *c = f64::from(l) * s;
        }
        let residual = self.transform(&coef, true);
        let mut out = [0u8; N];
        for ((o, &r), &p) in out.iter_mut().zip(&residual).zip(prediction) {
            *o = (p + r).round().clamp(0.0, 255.0) as u8;
        }
        out
    }

    /// Raster levels → zig-zag order.
    pub fn scan(&self, levels: &[i32; N]) -> [i32; N] {
        let mut z = [0; N];
        for (zi, &r) in z.iter_mut().zip(&self.zigzag) {
            *zi = levels[r];
        }
        z
    }

    /// Zig-zag order → raster levels.
    pub fn unscan(&self, scanned: &[i32; N]) -> [i32; N] {
        let mut levels = [0; N];
        for (&s, &r) in scanned.iter().zip(&self.zigzag) {
            levels[r] = s;
        }
        levels
    }
}

/// (run, level) pairs of `scanned[start..]`: zeros skipped before each nonzero level.
pub fn run_levels(scanned: &[i32; N], start: usize) -> Vec<(u32, i32)> {
    let mut pairs = Vec::new();
    let mut run = 0u32;
    for &l in &scanned[start.min(N)..] {
        if l == 0 {
            run += 1;
        } else {
            pairs.push((run, l));
            run = 0;
        }
    }
    pairs
}

/// The scan positions `start..64` filled from (run, level) pairs; an error when they run past
/// position 63 or a level is 0.
pub fn from_run_levels(pairs: &[(u32, i32)], start: usize) -> Result<[i32; N], String> {
    let mut scanned = [0i32; N];
    let mut pos = start;
    for &(run, level) in pairs {
        pos = pos.saturating_add(run as usize);
        if pos >= N {
            return Err(format!(
                "corrupt bitstream: a run of {run} zeros passes the end of an 8×8 block"
            ));
        }
        if level == 0 {
            return Err("corrupt bitstream: a zero level in a (run, level) pair".into());
        }
        scanned[pos] = level;
        pos += 1;
    }
    Ok(scanned)
}

/// Writes the (run, level) pairs of `scanned[start..]` and the end-of-block.
pub fn write_block(w: &mut BitWriter, scanned: &[i32; N], start: usize) {
    for (run, level) in run_levels(scanned, start) {
        w.put_ue(run + 1);
        w.put_ue(level.unsigned_abs() - 1);
        w.put_bit(level < 0);
    }
    w.put_ue(0);
}

/// Reads the pairs of one block up to its end-of-block; see [`write_block`].
pub fn read_block(r: &mut BitReader<'_>, start: usize) -> Result<[i32; N], String> {
    let mut pairs = Vec::new();
    loop {
        let code = r.ue()?;
        if code == 0 {
            break;
        }
        if pairs.len() >= N {
            return Err("corrupt bitstream: more than 64 coefficients in a block".into());
        }
        let magnitude = i64::from(r.ue()?) + 1;
        if magnitude > i64::from(MAX_LEVEL) {
            return Err(format!(
                "corrupt bitstream: level {magnitude} exceeds the largest level {MAX_LEVEL}"
            ));
        }
        let level = if r.bit()? { -magnitude } else { magnitude };
        pairs.push((code - 1, level as i32));
    }
    from_run_levels(&pairs, start)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// T.81 Figure A.6 / the zig-zag table of every JPEG decoder (libjpeg `jpeg_natural_order`).
    #[rustfmt::skip]
    const STANDARD_ZIGZAG: [usize; 64] = [
        0, 1, 8, 16, 9, 2, 3, 10, 17, 24, 32, 25, 18, 11, 4, 5,
        12, 19, 26, 33, 40, 48, 41, 34, 27, 20, 13, 6, 7, 14, 21, 28,
        35, 42, 49, 56, 57, 50, 43, 36, 29, 22, 15, 23, 30, 37, 44, 51,
        58, 59, 52, 45, 38, 31, 39, 46, 53, 60, 61, 54, 47, 55, 62, 63,
    ];

    #[test]
    fn zigzag_matches_the_standard_table() {
        assert_eq!(zigzag_order(), STANDARD_ZIGZAG);
    }

    #[test]
    fn dct_round_trip_is_exact_and_orthonormal() {
        let coder = BlockCoder::new(1.0, false);
        let mut x = [0.0; N];
        for (i, v) in x.iter_mut().enumerate() {
            *v = ((i * 37 + (i / 8) * 91) % 256) as f64 - 128.0;
        }
        let y = coder.transform(&x, false);
        let back = coder.transform(&y, true);
        for (a, b) in x.iter().zip(&back) {
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }
        // Parseval: energy preserved; DC = 8 × mean.
        let ex: f64 = x.iter().map(|v| v * v).sum();
        let ey: f64 = y.iter().map(|v| v * v).sum();
        assert!((ex - ey).abs() < 1e-6 * ex);
        let mean = x.iter().sum::<f64>() / 64.0;
        assert!((y[0] - 8.0 * mean).abs() < 1e-9);
    }

    #[test]
    fn quantizer_steps_follow_the_matrix() {
        // A constant block of +80 has DC 640 and nothing else; JPEG step 16 at quantizer 16
        // gives level 40; the flat matrix at quantizer 4 gives 160.
        let x = [80.0; N];
        let jpeg = BlockCoder::new(16.0, false).quantize(&x);
        assert_eq!(jpeg[0], 40);
        assert!(jpeg[1..].iter().all(|&l| l == 0));
        assert_eq!(BlockCoder::new(4.0, true).quantize(&x)[0], 160);
        let back = BlockCoder::new(16.0, false).reconstruct(&jpeg, &[48.0; N]);
        assert_eq!(back, [128u8; N]);
    }

    #[test]
    fn a_run_past_the_block_end_is_an_error() {
        assert!(from_run_levels(&[(70, 1)], 0).is_err());
        assert!(from_run_levels(&[(62, 1), (0, 2)], 1).is_err());
        assert!(from_run_levels(&[(0, 0)], 0).is_err());
    }

    proptest! {
        #[test]
        fn rle_and_entropy_round_trip(
            raw in proptest::collection::vec(-300i32..300, 64),
            sparsity in 0u32..4,
            start in 0usize..2,
        ) {
            // Mostly-zero blocks like quantized DCTs, and dense ones.
            let mut scanned = [0i32; N];
            for (i, (s, &v)) in scanned.iter_mut().zip(&raw).enumerate() {
                *s = if sparsity == 0 || (i as u32 * 7 + v.unsigned_abs()).is_multiple_of(sparsity + 1) { v } else { 0 };
            }
            let pairs = run_levels(&scanned, start);
            let mut expected = scanned;
            expected[..start].fill(0);
            prop_assert_eq!(from_run_levels(&pairs, start).unwrap(), expected);
            let mut w = BitWriter::new();
            write_block(&mut w, &scanned, start);
            write_block(&mut w, &scanned, start);
            let bytes = w.finish();
            let mut r = BitReader::new(&bytes);
            prop_assert_eq!(read_block(&mut r, start).unwrap(), expected);
            prop_assert_eq!(read_block(&mut r, start).unwrap(), expected);
            let coder = BlockCoder::new(1.0, false);
            prop_assert_eq!(coder.unscan(&coder.scan(&scanned)), scanned);
        }
    }
}
