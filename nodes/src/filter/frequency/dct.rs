//! `filter.dct`: the 8×8 blockwise orthonormal DCT-II of JPEG, and its inverse.
//!
//! Each 8×8 block `X` becomes `C·X·Cᵀ` (inverse: `Cᵀ·Y·C`) with the orthonormal DCT-II matrix
//! `C[k][n] = c(k)·cos((2n + 1)kπ/16)`, `c(0) = √(1/8)`, `c(k) = √(2/8)`. Both products are
//! written as sums of scaled 8-wide rows, so they vectorize. Strips of 8 rows run in parallel;
//! every block is computed by the same arithmetic whatever thread runs it.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, Value};
use rayon::prelude::*;

use super::{planes_image, to_planes};

/// Block side.
pub const BLOCK: usize = 8;

params! {
    /// Parameters of `filter.dct`.
    pub struct DctParams {
        /// false: forward DCT-II of every 8×8 block; true: inverse (DCT-III), which needs a
        /// width and height that are multiples of 8.
        inverse: bool = false,
    }
}

/// Blockwise 8×8 DCT (`filter.dct`). See [`dct_8x8`].
#[derive(Debug, Clone, PartialEq)]
pub struct Dct {
    inverse: bool,
}

impl Op for Dct {
    type Params = DctParams;
    const ID: &'static str = "filter.dct";
    const SUMMARY: &'static str =
        "8×8 blockwise orthonormal DCT-II (JPEG's transform) of an image, or its inverse.";
    const DOC: &'static str = r#"
Transforms every 8×8 block of every channel with the orthonormal 2-D DCT-II,
`Y(k, l) = c(k)·c(l)·Σ_x Σ_y X(x, y)·cos((2x + 1)kπ/16)·cos((2y + 1)lπ/16)`,
`c(0) = √(1/8)`, `c(k > 0) = 1/2`: the transform of JPEG, so the DC coefficient is 8 × the
block mean and the energy (sum of squares) of each block is preserved. `inverse: true` applies
the inverse (DCT-III) and gives the blocks back. The output is f32 with the input's channels.

Samples are taken as they are: no −128 level shift for u8 (JPEG subtracts 128 first; do that
with an arithmetic operator if wanted). Forward: a width or height that is not a multiple of 8
is padded by repeating the last column/row (as JPEG encoders do) and the output has the padded
size ⌈W/8⌉·8 × ⌈H/8⌉·8, so that the inverse recovers the padded image. Inverse: the size must be
a multiple of 8, otherwise an error.

Method: two 8×8 matrix products per block in f32 (matrix entries computed in f64). Agrees with
`cv2.dct` of each 8×8 CV_32F block within f32 rounding.

Reference: N. Ahmed, T. Natarajan, K. R. Rao, "Discrete Cosine Transform", IEEE Trans.
Computers C-23 (1974); ITU-T T.81 (JPEG) §A.3.3; OpenCV `cv::dct`.

Example:
    "coefficients": (op: "filter.dct", inputs: { "image": "gray.image" }, params: (inverse: false)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image (or coefficients, for the inverse), any pixel format.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Coefficients (or the image, for the inverse), f32, size rounded up to multiples of 8.",
        )]
    }

    fn new(params: DctParams) -> Result<Self, String> {
        Ok(Dct {
            inverse: params.inverse,
        })
    }
}

impl Operator for Dct {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = dct_8x8(image, self.inverse).map_err(|m| OpError::input("image", m))?;
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// Blockwise 8×8 orthonormal DCT-II (or, with `inverse`, DCT-III) of every channel of `image`,
/// as f32. The forward transform pads to multiples of 8 by repeating the last column and row;
/// the inverse needs multiples of 8 (else an error message).
pub fn dct_8x8(image: &Image, inverse: bool) -> Result<Image, String> {
    let (w, h) = (image.width(), image.height());
    if inverse && (!w.is_multiple_of(BLOCK) || !h.is_multiple_of(BLOCK)) {
        return Err(format!(
            "the inverse DCT needs a width and height that are multiples of 8, got {w}×{h}"
        ));
    }
    let (pw, ph) = (w.div_ceil(BLOCK) * BLOCK, h.div_ceil(BLOCK) * BLOCK);
    let planes = to_planes(image)
        .into_iter()
        .map(|plane| {
            let padded = pad_clamp(&plane, w, h, pw, ph);
            dct_plane(&padded, pw, ph, inverse)
        })
        .collect();
    planes_image(pw, ph, image.channels(), planes).map_err(|e| e.to_string())
}

/// `plane` (`w × h`) padded to `pw × ph` by repeating its last column and row.
fn pad_clamp(plane: &[f32], w: usize, h: usize, pw: usize, ph: usize) -> Vec<f32> {
    if (w, h) == (pw, ph) || w == 0 || h == 0 {
        return plane.to_vec();
    }
    let mut out = ocellus_engine::buffer::zeroed::<f32>(pw * ph);
    for (y, row) in out.chunks_exact_mut(pw).enumerate() {
        let src = &plane[y.min(h - 1) * w..][..w];
        row[..w].copy_from_slice(src);
        let last = src[w - 1];
        row[w..].fill(last);
    }
    out
}

/// The orthonormal 8-point DCT-II matrix `C[k][n]`.
pub fn dct_matrix() -> [[f32; BLOCK]; BLOCK] {
    dct_matrix_f64().map(|row| row.map(|v| v as f32))
}

/// The orthonormal 8-point DCT-II matrix `C[k][n] = c(k)·cos((2n + 1)kπ/16)` in f64.
pub fn dct_matrix_f64() -> [[f64; BLOCK]; BLOCK] {
    let mut c = [[0.0f64; BLOCK]; BLOCK];
    for (k, row) in c.iter_mut().enumerate() {
        let scale = if k == 0 { (0.125f64).sqrt() } else { 0.5 };
        for (n, v) in row.iter_mut().enumerate() {
            let angle = ((2 * n + 1) * k) as f64 * std::f64::consts::PI / 16.0;
            *v = scale * angle.cos();
        }
    }
    c
}

/// Blockwise 8×8 DCT of a `w × h` plane, `w` and `h` multiples of 8.
///
/// # Panics
/// If `plane.len() != w · h` or a side is not a multiple of 8.
pub fn dct_plane(plane: &[f32], w: usize, h: usize, inverse: bool) -> Vec<f32> {
    assert!(
        plane.len() == w * h && w.is_multiple_of(BLOCK) && h.is_multiple_of(BLOCK),
        "plane size"
    );
    let c = dct_matrix();
    // out = M·X·Mᵀ with M = C (forward) or Cᵀ (inverse); `mt` is Mᵀ.
    let mut m = c;
    let mut mt = c;
    for k in 0..BLOCK {
        for n in 0..BLOCK {
            mt[n][k] = c[k][n];
        }
    }
    if inverse {
        std::mem::swap(&mut m, &mut mt);
    }
    let mut out = ocellus_engine::buffer::zeroed::<f32>(w * h);
    if w == 0 || h == 0 {
        return out;
    }
    out.par_chunks_mut(BLOCK * w)
        .zip(plane.par_chunks(BLOCK * w))
        .for_each(|(dst, src)| {
            for bx in (0..w).step_by(BLOCK) {
                // tmp = X·Mᵀ: row r of tmp = Σ_n X[r][n] · Mᵀ[n].
                let mut tmp = [[0.0f32; BLOCK]; BLOCK];
                for (r, t) in tmp.iter_mut().enumerate() {
                    let x = &src[r * w + bx..r * w + bx + BLOCK];
                    for (n, &xn) in x.iter().enumerate() {
                        for (t, &mv) in t.iter_mut().zip(&mt[n]) {
                            *t += xn * mv;
                        }
                    }
                }
                // out = M·tmp: row k = Σ_r M[k][r] · tmp[r].
                for (k, mk) in m.iter().enumerate() {
                    let mut acc = [0.0f32; BLOCK];
                    for (&mkr, t) in mk.iter().zip(&tmp) {
                        for (a, &tv) in acc.iter_mut().zip(t) {
                            *a += mkr * tv;
                        }
                    }
                    dst[k * w + bx..k * w + bx + BLOCK].copy_from_slice(&acc);
                }
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::{random_u8, randoms};
    use ocellus_engine::value::Channels;
    use proptest::prelude::*;

    fn pattern(w: usize, h: usize) -> Vec<f32> {
        (0..h)
            .flat_map(|y| (0..w).map(move |x| ((x * 37 + y * 91 + x * y * 13) % 256) as f32))
            .collect()
    }

    #[test]
    fn agrees_with_opencv() {
        // cv2.dct(img.astype(np.float32)) (OpenCV 5.0) on img[y, x] = (x·37 + y·91 + x·y·13)
        // mod 256, 8×8; first two rows of coefficients.
        let out = dct_plane(&pattern(8, 8), 8, 8, false);
        for (i, (&a, &b)) in out.iter().zip(&OPENCV_ROWS_0_1).enumerate() {
            assert!((a - b).abs() < 2e-3, "coefficient {i}: {a} vs OpenCV {b}");
        }
    }

    #[rustfmt::skip]
    const OPENCV_ROWS_0_1: [f32; 16] = [
        1082.0, -73.403, -108.112, 0.874, 0.0, 7.015, -93.765, -140.364,
        -98.871, 4.966, -31.899, -1.918, -87.185, 71.016, 19.414, 43.42,
    ];

    #[test]
    fn dc_is_eight_times_the_mean_and_constant_blocks_have_only_dc() {
        let (w, h) = (16, 8);
        let p: Vec<f32> = randoms(3, w * h)
            .iter()
            .map(|&r| (r * 255.0) as f32)
            .collect();
        let out = dct_plane(&p, w, h, false);
        for bx in [0, 8] {
            let mean: f32 = (0..8)
                .flat_map(|y| (0..8).map(move |x| (x, y)))
                .map(|(x, y)| p[y * w + bx + x])
                .sum::<f32>()
                / 64.0;
            assert!((out[bx] - 8.0 * mean).abs() < 1e-3);
        }
        let constant = dct_plane(&[5.0; 64], 8, 8, false);
        assert!((constant[0] - 40.0).abs() < 1e-5);
        assert!(constant[1..].iter().all(|v| v.abs() < 1e-5));
    }

    #[test]
    fn padding_and_sizes() {
        // 10×3 pads to 16×8 by repeating the edge.
        let img = random_u8(10, 3, Channels::Rgb, 2);
        let out = dct_8x8(&img, false).unwrap();
        assert_eq!(
            (out.width(), out.height(), out.channels()),
            (16, 8, Channels::Rgb)
        );
        let back = dct_8x8(&out, true).unwrap();
        let b = back.as_f32().unwrap();
        let s = img.as_u8().unwrap();
        for y in 0..8 {
            for x in 0..16 {
                for c in 0..3 {
                    let src = s[(y.min(2) * 10 + x.min(9)) * 3 + c];
                    let got = b[(y * 16 + x) * 3 + c];
                    assert!((got - f32::from(src)).abs() < 1e-3, "({x}, {y}, {c})");
                }
            }
        }
        let err = dct_8x8(&img, true).unwrap_err();
        assert!(err.contains("multiples of 8"), "{err}");
        let one = Image::from_u16(1, 1, Channels::Gray, vec![1000]).unwrap();
        let out = dct_8x8(&one, false).unwrap();
        assert_eq!(out.width(), 8);
        assert!((out.as_f32().unwrap()[0] - 8000.0).abs() < 1e-2);
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        assert_eq!(dct_8x8(&empty, false).unwrap().width(), 0);
        assert_eq!(dct_8x8(&empty, true).unwrap().width(), 0);
    }

    #[test]
    fn operator_runs() {
        let op = Dct::new(DctParams { inverse: true }).unwrap();
        let img = random_u8(12, 8, Channels::Gray, 1);
        let specs = Dct::inputs();
        let ctx = RunContext {
            node: "d".into(),
            threads: 1,
            element: None,
        };
        let err = op
            .run(&ctx, &Inputs::new(&specs, &[Some(Value::image(img))]))
            .unwrap_err();
        assert!(err.to_string().contains("multiples of 8"), "{err}");
    }

    #[test]
    fn output_is_identical_for_any_thread_count() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let img = random_u8(203, 99, Channels::Rgb, 4);
        let run = || dct_8x8(&img, false).unwrap();
        assert_eq!(pool(1).install(run), pool(3).install(run));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        #[test]
        fn orthonormal_and_invertible(bw in 1usize..5, bh in 1usize..5, seed in any::<u64>()) {
            let (w, h) = (bw * 8, bh * 8);
            let p: Vec<f32> = randoms(seed, w * h).iter().map(|&r| (r * 512.0 - 256.0) as f32).collect();
            let out = dct_plane(&p, w, h, false);
            let energy = |v: &[f32]| v.iter().map(|&x| f64::from(x).powi(2)).sum::<f64>();
            prop_assert!((energy(&out) - energy(&p)).abs() <= 1e-5 * energy(&p));
            let back = dct_plane(&out, w, h, true);
            for (a, b) in back.iter().zip(&p) {
                prop_assert!((a - b).abs() < 1e-3);
            }
            // Linearity.
            let doubled: Vec<f32> = p.iter().map(|&x| 2.0 * x).collect();
            let out2 = dct_plane(&doubled, w, h, false);
            for (a, b) in out2.iter().zip(&out) {
                prop_assert!((a - 2.0 * b).abs() < 1e-3);
            }
        }
    }
}
