//! `filter.haar`: the multi-level 2-D orthonormal Haar wavelet transform in Mallat's layout,
//! and its inverse.
//!
//! One level on the current approximation region (`w × h`, top-left): every row becomes
//! `[(a + b)/√2 …, (a − b)/√2 …]` over its pairs (a, b) = (x₂ᵢ, x₂ᵢ₊₁), then every column the
//! same. Both passes are row-wise loops (the column pass combines rows 2i and 2i + 1 into rows i
//! and h/2 + i), parallel over rows with a fixed assignment of work to rows, so results are
//! bit-identical for any thread count.

use std::f32::consts::FRAC_1_SQRT_2;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, Value};
use rayon::prelude::*;

use super::{planes_image, to_planes};

/// Most levels accepted (a 2³⁰-pixel side is far beyond any image).
pub const MAX_LEVELS: u32 = 30;

params! {
    /// Parameters of `filter.haar`.
    pub struct HaarParams {
        /// Decomposition levels, 1..=30; width and height must be divisible by 2^levels.
        levels: u32 = 1 => [min = 1, max = 30],
        /// false: forward transform; true: inverse (input in the layout the forward writes).
        inverse: bool = false,
    }
}

/// Multi-level 2-D Haar transform (`filter.haar`). See [`haar`].
#[derive(Debug, Clone, PartialEq)]
pub struct Haar {
    levels: u32,
    inverse: bool,
}

impl Op for Haar {
    type Params = HaarParams;
    const ID: &'static str = "filter.haar";
    const SUMMARY: &'static str =
        "Multi-level 2-D orthonormal Haar wavelet transform (Mallat layout), or its inverse.";
    const DOC: &'static str = r#"
Applies `levels` levels of the separable orthonormal Haar wavelet transform to every channel and
writes the coefficients in Mallat's layout in one f32 image of the input's size: after one level
the top-left quadrant holds the approximation (low-pass along x and y), the top-right the
detail that is high-pass along x (vertical edges), the bottom-left high-pass along y
(horizontal edges) and the bottom-right high-pass along both; each further level splits the
top-left quadrant again. Filters: low (a + b)/√2, high (a − b)/√2 on pairs (x₂ᵢ, x₂ᵢ₊₁) — the
coefficients of PyWavelets' `dwt2(..., "haar")`. Orthonormal: the energy (sum of squares) is
preserved, and `inverse: true` reconstructs the image exactly up to f32 rounding. A constant
image has nonzero coefficients only in the approximation (2^levels times the value).

Width and height must be divisible by 2^levels (an error otherwise; pad or crop first). Samples
are taken as they are (u8/u16 not rescaled); the output is f32 with the input's channels.

Reference: A. Haar (1910); S. Mallat, "A theory for multiresolution signal decomposition: the
wavelet representation", IEEE PAMI 11 (1989); PyWavelets `dwt2`/`idwt2`.

Example:
    "wavelets": (op: "filter.haar", inputs: { "image": "gray.image" }, params: (levels: 3)),
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
            "Coefficients in Mallat's layout (or the image, for the inverse), f32, same size.",
        )]
    }

    fn new(params: HaarParams) -> Result<Self, String> {
        let HaarParams { levels, inverse } = params;
        if !(1..=MAX_LEVELS).contains(&levels) {
            return Err(format!(
                "`levels` must be between 1 and {MAX_LEVELS}, got {levels}"
            ));
        }
        Ok(Haar { levels, inverse })
    }
}

impl Operator for Haar {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = haar(image, self.levels, self.inverse).map_err(|m| OpError::input("image", m))?;
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// `levels` levels of the 2-D Haar transform (or its inverse) of every channel of `image`, as
/// f32 in Mallat's layout. Errors when a side is not divisible by 2^levels.
pub fn haar(image: &Image, levels: u32, inverse: bool) -> Result<Image, String> {
    let (w, h) = (image.width(), image.height());
    let step = 1usize
        .checked_shl(levels)
        .filter(|_| levels <= MAX_LEVELS)
        .ok_or_else(|| format!("`levels` must be at most {MAX_LEVELS}, got {levels}"))?;
    if !w.is_multiple_of(step) || !h.is_multiple_of(step) {
        return Err(format!(
            "{levels} Haar levels need a width and height divisible by {step}, got {w}×{h}"
        ));
    }
    let planes = to_planes(image)
        .into_iter()
        .map(|mut plane| {
            haar_plane(&mut plane, w, h, levels, inverse);
            plane
        })
        .collect();
    planes_image(w, h, image.channels(), planes).map_err(|e| e.to_string())
}

/// In-place [`haar`] of one `w × h` plane whose sides are divisible by 2^levels.
///
/// # Panics
/// If `plane.len() != w · h` or a side is not divisible by 2^levels.
pub fn haar_plane(plane: &mut [f32], w: usize, h: usize, levels: u32, inverse: bool) {
    let step = 1usize << levels;
    assert!(
        plane.len() == w * h && w.is_multiple_of(step) && h.is_multiple_of(step),
        "plane size"
    );
    if w == 0 || h == 0 {
        return;
    }
    if inverse {
        for level in (0..levels).rev() {
            let (lw, lh) = (w >> level, h >> level);
            inverse_columns(plane, w, lw, lh);
            inverse_rows(plane, w, lw, lh);
        }
    } else {
        for level in 0..levels {
            let (lw, lh) = (w >> level, h >> level);
            forward_rows(plane, w, lw, lh);
            forward_columns(plane, w, lw, lh);
        }
    }
}

/// Rows `0..lh`, columns `0..lw` (stride `w`): pairs → [low…, high…].
fn forward_rows(plane: &mut [f32], w: usize, lw: usize, lh: usize) {
    let half = lw / 2;
    plane[..lh * w]
        .par_chunks_mut(w)
        .with_min_len(8)
        .for_each_init(
            || vec![0.0f32; lw],
            |tmp, row| {
                let (lo, hi) = tmp.split_at_mut(half);
                for ((pair, l), h) in row[..lw].chunks_exact(2).zip(lo).zip(hi) {
                    *l = (pair[0] + pair[1]) * FRAC_1_SQRT_2;
                    *h = (pair[0] - pair[1]) * FRAC_1_SQRT_2;
                }
                row[..lw].copy_from_slice(tmp);
            },
        );
}

/// Inverse of [`forward_rows`].
fn inverse_rows(plane: &mut [f32], w: usize, lw: usize, lh: usize) {
    let half = lw / 2;
    plane[..lh * w]
        .par_chunks_mut(w)
        .with_min_len(8)
        .for_each_init(
            || vec![0.0f32; lw],
            |tmp, row| {
                let (lo, hi) = row[..lw].split_at(half);
                for ((pair, &l), &h) in tmp.chunks_exact_mut(2).zip(lo).zip(hi) {
                    pair[0] = (l + h) * FRAC_1_SQRT_2;
                    pair[1] = (l - h) * FRAC_1_SQRT_2;
                }
                row[..lw].copy_from_slice(tmp);
            },
        );
}

/// Columns: rows (2i, 2i + 1) → rows i (low) and lh/2 + i (high), over columns `0..lw`.
fn forward_columns(plane: &mut [f32], w: usize, lw: usize, lh: usize) {
    let src: Vec<f32> = plane[..lh * w].to_vec();
    let (top, bottom) = plane[..lh * w].split_at_mut(lh / 2 * w);
    top.par_chunks_mut(w)
        .zip(bottom.par_chunks_mut(w))
        .enumerate()
        .with_min_len(8)
        .for_each(|(i, (lo, hi))| {
            let a = &src[2 * i * w..2 * i * w + lw];
            let b = &src[(2 * i + 1) * w..(2 * i + 1) * w + lw];
            for (((l, h), &a), &b) in lo[..lw].iter_mut().zip(&mut hi[..lw]).zip(a).zip(b) {
                *l = (a + b) * FRAC_1_SQRT_2;
                *h = (a - b) * FRAC_1_SQRT_2;
            }
        });
}

/// Inverse of [`forward_columns`].
fn inverse_columns(plane: &mut [f32], w: usize, lw: usize, lh: usize) {
    let src: Vec<f32> = plane[..lh * w].to_vec();
    let half = lh / 2;
    plane[..lh * w]
        .par_chunks_mut(2 * w)
        .enumerate()
        .with_min_len(4)
        .for_each(|(i, pair)| {
            let lo = &src[i * w..i * w + lw];
            let hi = &src[(half + i) * w..(half + i) * w + lw];
            let (a, b) = pair.split_at_mut(w);
            for (((a, b), &l), &h) in a[..lw].iter_mut().zip(&mut b[..lw]).zip(lo).zip(hi) {
                *a = (l + h) * FRAC_1_SQRT_2;
                *b = (l - h) * FRAC_1_SQRT_2;
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::{random_u8, randoms};
    use ocellus_engine::value::Channels;
    use proptest::prelude::*;

    #[test]
    fn two_by_two_by_hand() {
        // [[1, 2], [3, 4]]: rows → [3, −1]/√2, [7, −1]/√2; columns → LL 5, HL −1, LH −2, HH 0.
        let mut p = vec![1.0f32, 2.0, 3.0, 4.0];
        haar_plane(&mut p, 2, 2, 1, false);
        let expected = [5.0, -1.0, -2.0, 0.0];
        for (a, b) in p.iter().zip(expected) {
            assert!((a - b).abs() < 1e-6, "{p:?}");
        }
        haar_plane(&mut p, 2, 2, 1, true);
        for (a, b) in p.iter().zip([1.0, 2.0, 3.0, 4.0]) {
            assert!((a - b).abs() < 1e-6, "{p:?}");
        }
    }

    #[test]
    fn constant_image_has_only_approximation_coefficients() {
        let (w, h) = (16, 8);
        for levels in 1..=3 {
            let mut p = vec![3.0f32; w * h];
            haar_plane(&mut p, w, h, levels, false);
            let (aw, ah) = (w >> levels, h >> levels);
            let value = 3.0 * (1 << levels) as f32;
            for y in 0..h {
                for x in 0..w {
                    let v = p[y * w + x];
                    if x < aw && y < ah {
                        assert!((v - value).abs() < 1e-4, "level {levels} ({x}, {y}): {v}");
                    } else {
                        assert!(v.abs() < 1e-5, "level {levels} ({x}, {y}): {v}");
                    }
                }
            }
        }
    }

    #[test]
    fn sizes_are_checked() {
        let img = random_u8(12, 8, Channels::Rgb, 1);
        assert!(haar(&img, 2, false).is_ok());
        let err = haar(&img, 3, false).unwrap_err();
        assert!(err.contains("divisible by 8"), "{err}");
        let one = Image::from_f32(1, 1, Channels::Gray, vec![1.0]).unwrap();
        assert!(haar(&one, 1, false).is_err());
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        assert_eq!(haar(&empty, 4, true).unwrap().width(), 0);
        assert!(
            Haar::new(HaarParams {
                levels: 0,
                inverse: false
            })
            .is_err()
        );
        assert!(
            Haar::new(HaarParams {
                levels: 31,
                inverse: false
            })
            .is_err()
        );
        // Channels are independent: channel 1 of an RGB image equals the gray transform.
        let out = haar(&img, 2, false).unwrap();
        let green: Vec<f32> = img
            .as_u8()
            .unwrap()
            .iter()
            .skip(1)
            .step_by(3)
            .map(|&v| f32::from(v))
            .collect();
        let mut alone = green.clone();
        haar_plane(&mut alone, 12, 8, 2, false);
        let got: Vec<f32> = out
            .as_f32()
            .unwrap()
            .iter()
            .skip(1)
            .step_by(3)
            .copied()
            .collect();
        assert_eq!(got, alone);
    }

    #[test]
    fn operator_runs_and_round_trips() {
        let img = random_u8(16, 16, Channels::Gray, 3);
        let ctx = RunContext {
            node: "h".into(),
            threads: 1,
            element: None,
        };
        let specs = Haar::inputs();
        let fwd = Haar::new(HaarParams {
            levels: 4,
            inverse: false,
        })
        .unwrap();
        let inv = Haar::new(HaarParams {
            levels: 4,
            inverse: true,
        })
        .unwrap();
        let mut out = fwd
            .run(
                &ctx,
                &Inputs::new(&specs, &[Some(Value::image(img.clone()))]),
            )
            .unwrap();
        let coefficients = out.take("image").unwrap();
        let mut out = inv
            .run(&ctx, &Inputs::new(&specs, &[Some(coefficients)]))
            .unwrap();
        let Some(Value::Image(back)) = out.take("image") else {
            panic!("expected an image");
        };
        for (a, &b) in back.as_f32().unwrap().iter().zip(img.as_u8().unwrap()) {
            assert!((a - f32::from(b)).abs() < 1e-3);
        }
        let odd = random_u8(10, 16, Channels::Gray, 3);
        let err = fwd
            .run(&ctx, &Inputs::new(&specs, &[Some(Value::image(odd))]))
            .unwrap_err();
        assert!(err.to_string().contains("divisible by 16"), "{err}");
    }

    #[test]
    fn output_is_identical_for_any_thread_count() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let img = random_u8(256, 136, Channels::Rgb, 4);
        let run = || haar(&img, 3, false).unwrap();
        assert_eq!(pool(1).install(run), pool(3).install(run));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        #[test]
        fn perfect_reconstruction_and_energy(
            levels in 1u32..4,
            bw in 1usize..5,
            bh in 1usize..5,
            seed in any::<u64>(),
        ) {
            let (w, h) = (bw << levels, bh << levels);
            let p: Vec<f32> = randoms(seed, w * h).iter().map(|&r| (r * 255.0) as f32).collect();
            let mut t = p.clone();
            haar_plane(&mut t, w, h, levels, false);
            let energy = |v: &[f32]| v.iter().map(|&x| f64::from(x).powi(2)).sum::<f64>();
            prop_assert!((energy(&t) - energy(&p)).abs() <= 1e-5 * energy(&p).max(1.0));
            haar_plane(&mut t, w, h, levels, true);
            for (a, b) in t.iter().zip(&p) {
                prop_assert!((a - b).abs() < 1e-3, "{a} vs {b}");
            }
        }
    }
}
