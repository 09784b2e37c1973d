//! `filter.grayscale`: colour to luma.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

/// Pixels per parallel task.
const PIXELS_PER_TASK: usize = 1 << 16;

/// Fractional bits of the integer luma coefficients (OpenCV's `yuv_shift`).
const COEFF_BITS: u32 = 14;

param_enum! {
    /// Which luma weights to use.
    pub enum LumaStandard {
        /// ITU-R BT.601: Y = 0.299 R + 0.587 G + 0.114 B (OpenCV's `COLOR_RGB2GRAY`).
        Bt601 = "bt601",
        /// ITU-R BT.709: Y = 0.2126 R + 0.7152 G + 0.0722 B.
        Bt709 = "bt709",
    }
}

impl LumaStandard {
    /// The weights of R, G and B; they sum to 1.
    pub fn weights(self) -> [f64; 3] {
        match self {
            LumaStandard::Bt601 => [0.299, 0.587, 0.114],
            LumaStandard::Bt709 => [0.2126, 0.7152, 0.0722],
        }
    }
}

params! {
    /// Parameters of `filter.grayscale`.
    pub struct GrayscaleParams {
        /// Luma weights: "bt601" (OpenCV's cvtColor RGB2GRAY) or "bt709" (HDTV).
        standard: LumaStandard = LumaStandard::Bt601,
    }
}

/// Colour to gray conversion (`filter.grayscale`). See [`grayscale`].
#[derive(Debug, Clone, PartialEq)]
pub struct Grayscale {
    standard: LumaStandard,
}

impl Op for Grayscale {
    type Params = GrayscaleParams;
    const ID: &'static str = "filter.grayscale";
    const SUMMARY: &'static str = "Converts an image to gray (luma), keeping its sample type.";
    const DOC: &'static str = r#"
Converts an RGB or RGBA image to a one-channel gray image of the same sample type:
Y = wr·R + wg·G + wb·B with the weights of ITU-R BT.601 (0.299, 0.587, 0.114; the default) or
BT.709 (0.2126, 0.7152, 0.0722). Alpha is ignored (the colour is not composited over anything).
A gray input is passed through unchanged.

Method: as OpenCV's `cvtColor(COLOR_RGB2GRAY)`. For u8 and u16 the weights are 14-bit integers
(each rounded, summing to 2¹⁴; 4899, 9617, 1868 for BT.601) and Y = (Σ w·c + 2¹³) >> 14, which
matches OpenCV bit for bit; f32 is the plain weighted sum in f32. Samples are not linearised:
the weights apply to the stored (gamma-encoded) values, as in OpenCV.

Reference: OpenCV `cv::cvtColor`; ITU-R BT.601-7, BT.709-6.

Example:
    "gray": (op: "filter.grayscale", inputs: { "image": "card.image" }, params: (standard: "bt709")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to convert: gray, RGB or RGBA, any sample type.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "One-channel gray image, same size and sample type as the input.",
        )]
    }

    fn new(params: GrayscaleParams) -> Result<Self, String> {
        Ok(Grayscale {
            standard: params.standard,
        })
    }
}

impl Operator for Grayscale {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        if image.channels() == Channels::Gray {
            return Ok(Outputs::new().with("image", Value::Image(image.clone())));
        }
        let gray = grayscale(image, self.standard)
            .map_err(|e| OpError::failed(format!("building the gray image: {e}")))?;
        Ok(Outputs::new().with("image", Value::image(gray)))
    }
}

/// The integer weights of R, G and B with 14 fractional bits: each weight rounded,
/// then the largest corrected so that they sum to exactly 2¹⁴ (white stays white).
pub fn integer_weights(standard: LumaStandard) -> [u32; 3] {
    let one = 1u32 << COEFF_BITS;
    let mut coeffs = standard
        .weights()
        .map(|w| (w * f64::from(one)).round() as u32);
    let sum: u32 = coeffs.iter().sum();
    let largest = (0..3).max_by_key(|&i| coeffs[i]).unwrap_or(1);
    coeffs[largest] = (coeffs[largest] + one).saturating_sub(sum);
    coeffs
}

/// The gray version of `image` (one channel, same size and sample type); a gray image is
/// returned as a copy. Alpha is ignored.
pub fn grayscale(
    image: &Image,
    standard: LumaStandard,
) -> Result<Image, ocellus_engine::value::ValueError> {
    let stride = image.channels().count();
    if stride == 1 {
        return Ok(image.clone());
    }
    let weights = standard.weights().map(|w| w as f32);
    // Strides and coefficients are constants in each instance: LLVM then vectorizes the
    // interleaved loads and multiplies in 16-bit lanes (`pmaddwd`); with coefficients known
    // only at run time it keeps the loop scalar.
    let data = match (image.data(), stride, standard) {
        (PixelData::U8(src), 3, LumaStandard::Bt601) => PixelData::U8(bt601::<_, 3>(src)),
        (PixelData::U8(src), _, LumaStandard::Bt601) => PixelData::U8(bt601::<_, 4>(src)),
        (PixelData::U8(src), 3, LumaStandard::Bt709) => PixelData::U8(bt709::<_, 3>(src)),
        (PixelData::U8(src), _, LumaStandard::Bt709) => PixelData::U8(bt709::<_, 4>(src)),
        (PixelData::U16(src), 3, LumaStandard::Bt601) => PixelData::U16(bt601::<_, 3>(src)),
        (PixelData::U16(src), _, LumaStandard::Bt601) => PixelData::U16(bt601::<_, 4>(src)),
        (PixelData::U16(src), 3, LumaStandard::Bt709) => PixelData::U16(bt709::<_, 3>(src)),
        (PixelData::U16(src), _, LumaStandard::Bt709) => PixelData::U16(bt709::<_, 4>(src)),
        (PixelData::F32(src), 3, _) => PixelData::F32(float_luma::<3>(src, weights)),
        (PixelData::F32(src), _, _) => PixelData::F32(float_luma::<4>(src, weights)),
    };
    Image::new(image.width(), image.height(), Channels::Gray, data)
}

/// [`integer_weights`] of BT.601 and BT.709, as constants (a test checks they agree).
const BT601_Q14: [u32; 3] = [4899, 9617, 1868];
const BT709_Q14: [u32; 3] = [3483, 11718, 1183];

fn bt601<T: IntegerSample, const S: usize>(src: &[T]) -> Vec<T> {
    integer_luma::<T, S, { BT601_Q14[0] }, { BT601_Q14[1] }, { BT601_Q14[2] }>(src)
}

fn bt709<T: IntegerSample, const S: usize>(src: &[T]) -> Vec<T> {
    integer_luma::<T, S, { BT709_Q14[0] }, { BT709_Q14[1] }, { BT709_Q14[2] }>(src)
}

/// Integer samples: u8 and u16.
trait IntegerSample: Copy + Default + Send + Sync + Into<u32> {
    /// From a value known to fit.
    fn narrow(v: u32) -> Self;
}

impl IntegerSample for u8 {
    fn narrow(v: u32) -> Self {
        v as u8
    }
}

impl IntegerSample for u16 {
    fn narrow(v: u32) -> Self {
        v as u16
    }
}

/// `(r·CR + g·CG + b·CB + 2¹³) >> 14` for every pixel of `S` samples, in parallel. The result
/// fits the sample type because the coefficients sum to 2¹⁴.
fn integer_luma<T: IntegerSample, const S: usize, const CR: u32, const CG: u32, const CB: u32>(
    src: &[T],
) -> Vec<T> {
    let mut dst = ocellus_engine::buffer::zeroed::<T>(src.len() / S);
    dst.par_chunks_mut(PIXELS_PER_TASK)
        .zip(src.par_chunks(PIXELS_PER_TASK * S))
        .for_each(|(out, pixels)| {
            let round = 1u32 << (COEFF_BITS - 1);
            for (o, p) in out.iter_mut().zip(pixels.chunks_exact(S)) {
                let y = p[0].into() * CR + p[1].into() * CG + p[2].into() * CB + round;
                *o = T::narrow(y >> COEFF_BITS);
            }
        });
    dst
}

/// `wr·r + wg·g + wb·b` for every pixel of `S` f32 samples, in parallel.
fn float_luma<const S: usize>(src: &[f32], weights: [f32; 3]) -> Vec<f32> {
    let mut dst = vec![0.0; src.len() / S];
    dst.par_chunks_mut(PIXELS_PER_TASK)
        .zip(src.par_chunks(PIXELS_PER_TASK * S))
        .for_each(|(out, pixels)| {
            let [wr, wg, wb] = weights;
            for (o, p) in out.iter_mut().zip(pixels.chunks_exact(S)) {
                *o = wr * p[0] + wg * p[1] + wb * p[2];
            }
        });
    dst
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::op::Inputs;

    fn rgb_u8(pixels: &[[u8; 3]]) -> Image {
        let data = pixels.iter().flatten().copied().collect();
        Image::from_u8(pixels.len(), 1, Channels::Rgb, data).unwrap()
    }

    fn gray_u8(image: &Image, standard: LumaStandard) -> Vec<u8> {
        let out = grayscale(image, standard).unwrap();
        assert_eq!(out.channels(), Channels::Gray);
        assert_eq!((out.width(), out.height()), (image.width(), image.height()));
        out.as_u8().unwrap().to_vec()
    }

    #[test]
    fn integer_weights_are_opencv_and_sum_to_one() {
        assert_eq!(integer_weights(LumaStandard::Bt601), [4899, 9617, 1868]);
        assert_eq!(integer_weights(LumaStandard::Bt709), [3483, 11718, 1183]);
        assert_eq!(integer_weights(LumaStandard::Bt601), BT601_Q14);
        assert_eq!(integer_weights(LumaStandard::Bt709), BT709_Q14);
        for s in LumaStandard::ALL {
            assert_eq!(integer_weights(*s).iter().sum::<u32>(), 1 << 14);
        }
    }

    #[test]
    fn bt601_u8_matches_opencv_values() {
        // OpenCV 5.0 cvtColor(COLOR_RGB2GRAY) gives exactly these.
        let img = rgb_u8(&[
            [255, 0, 0],
            [0, 255, 0],
            [0, 0, 255],
            [255, 255, 255],
            [0, 0, 0],
            [128, 128, 128],
            [255, 255, 0],
        ]);
        assert_eq!(
            gray_u8(&img, LumaStandard::Bt601),
            [76, 150, 29, 255, 0, 128, 226]
        );
    }

    #[test]
    fn bt601_u8_formula_on_mixed_pixels() {
        // (r·4899 + g·9617 + b·1868 + 8192) >> 14, worked by hand (and OpenCV agrees):
        // (10, 200, 30): 48990 + 1923400 + 56040 + 8192 = 2036622 → 124
        // (123, 45, 67): 602577 + 432765 + 125156 + 8192 = 1168690 → 71
        let img = rgb_u8(&[[10, 200, 30], [123, 45, 67]]);
        assert_eq!(gray_u8(&img, LumaStandard::Bt601), [124, 71]);
    }

    #[test]
    fn bt709_u8_values() {
        // Red: 255·3483 + 8192 = 896357 → 54; green: 255·11718 + 8192 = 2996282 → 182;
        // blue: 255·1183 + 8192 = 309857 → 18.
        let img = rgb_u8(&[[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]]);
        assert_eq!(gray_u8(&img, LumaStandard::Bt709), [54, 182, 18, 255]);
    }

    #[test]
    fn rgba_ignores_alpha() {
        let rgba = Image::from_u8(
            3,
            1,
            Channels::Rgba,
            vec![255, 0, 0, 0, 255, 0, 0, 255, 10, 200, 30, 77],
        )
        .unwrap();
        assert_eq!(gray_u8(&rgba, LumaStandard::Bt601), [76, 76, 124]);
    }

    #[test]
    fn u16_uses_the_same_integer_formula() {
        let img = Image::from_u16(
            3,
            1,
            Channels::Rgb,
            vec![65535, 0, 0, 65535, 65535, 65535, 1000, 2000, 3000],
        )
        .unwrap();
        let out = grayscale(&img, LumaStandard::Bt601).unwrap();
        // As OpenCV: 65535·4899 + 8192 = 321064157 → 19596; 1000·4899 + 2000·9617 + 3000·1868 +
        // 8192 = 29745192 → 1815.
        assert_eq!(out.as_u16().unwrap(), [19596, 65535, 1815]);
    }

    #[test]
    fn f32_is_the_weighted_sum() {
        let img = Image::from_f32(2, 1, Channels::Rgb, vec![1.0, 0.0, 0.0, 0.2, 0.4, 0.6]).unwrap();
        for s in LumaStandard::ALL {
            let out = grayscale(&img, *s).unwrap();
            let [wr, wg, wb] = s.weights();
            let got = out.as_f32().unwrap();
            assert!((f64::from(got[0]) - wr).abs() < 1e-7);
            let expected = wr * 0.2 + wg * 0.4 + wb * 0.6;
            assert!((f64::from(got[1]) - expected).abs() < 1e-6);
        }
    }

    #[test]
    fn gray_passes_through_the_operator_unchanged() {
        let img = Image::from_u8(2, 2, Channels::Gray, vec![1, 2, 3, 4]).unwrap();
        let value = Value::image(img);
        let op = Grayscale::new(GrayscaleParams::default()).unwrap();
        let specs = Grayscale::inputs();
        let values = [Some(value.clone())];
        let ctx = RunContext {
            node: "g".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let (Some(Value::Image(got)), Value::Image(original)) = (out.take("image"), &value) else {
            panic!("expected an image");
        };
        assert!(std::sync::Arc::ptr_eq(&got, original));
    }

    #[test]
    fn operator_converts_and_reports_wrong_input_types() {
        let op = Grayscale::new(GrayscaleParams {
            standard: LumaStandard::Bt709,
        })
        .unwrap();
        let specs = Grayscale::inputs();
        let ctx = RunContext {
            node: "g".into(),
            threads: 1,
            element: None,
        };
        let values = [Some(Value::image(rgb_u8(&[[0, 255, 0]])))];
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Image(gray)) = out.take("image") else {
            panic!("expected an image");
        };
        assert_eq!(gray.as_u8().unwrap(), [182]);
        let values = [Some(Value::Scalar(1.0))];
        let err = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap_err();
        assert!(err.to_string().contains("expected Image"), "{err}");
    }

    #[test]
    fn empty_images_stay_empty() {
        let img = Image::from_u8(0, 3, Channels::Rgb, vec![]).unwrap();
        let out = grayscale(&img, LumaStandard::Bt601).unwrap();
        assert_eq!(
            (out.width(), out.height(), out.channels()),
            (0, 3, Channels::Gray)
        );
    }

    #[test]
    fn large_images_match_the_per_pixel_formula() {
        // Spans several parallel tasks.
        let (w, h) = (517, 300);
        let data: Vec<u8> = (0..w * h * 3).map(|i| (i * 7919 % 251) as u8).collect();
        let img = Image::from_u8(w, h, Channels::Rgb, data.clone()).unwrap();
        let got = gray_u8(&img, LumaStandard::Bt601);
        for (i, p) in data.chunks_exact(3).enumerate() {
            let [r, g, b] = [p[0], p[1], p[2]].map(u32::from);
            let expected = (r * 4899 + g * 9617 + b * 1868 + 8192) >> 14;
            assert_eq!(u32::from(got[i]), expected, "pixel {i}");
        }
    }
}
