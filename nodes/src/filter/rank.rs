//! `filter.min` and `filter.max`: the minimum or maximum over a rectangular window, per channel.
//!
//! These rank filters are grayscale erosion and dilation with a full rectangular structuring
//! element, so they call [`erode`] and [`dilate`] of the morphology module (van Herk /
//! Gil-Werman running extrema, cost independent of the window size). They exist as their own
//! operators because "the local minimum over a w × h window" is how many pipelines think of
//! them, without structuring elements or iterations.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, Value};

use super::morphology::{MAX_KSIZE, MorphBorder, Shape, StructuringElement, dilate, erode};

params! {
    /// Parameters of `filter.min` and `filter.max`.
    pub struct RankParams {
        /// Window size `[width, height]`, each 1..=1023, odd or even. The window of output pixel
        /// (x, y) starts at (x − ⌊width/2⌋, y − ⌊height/2⌋), OpenCV's default anchor.
        ksize: [u32; 2] = [3, 3] => [min = 1, max = 1023, unit = "px"],
        /// How pixels outside the image are read; "neutral" (default) lets them never win (as
        /// OpenCV's erode/dilate default), the others are OpenCV's border types.
        border: MorphBorder = MorphBorder::Neutral,
    }
}

/// The checked window shared by both operators.
fn window(params: RankParams) -> Result<(StructuringElement, MorphBorder), String> {
    let RankParams { ksize, border } = params;
    for (axis, k) in ["width", "height"].iter().zip(ksize) {
        if !(1..=MAX_KSIZE).contains(&k) {
            return Err(format!(
                "`ksize` {axis} must be between 1 and {MAX_KSIZE} px, got {k}"
            ));
        }
    }
    let element = StructuringElement::new(Shape::Rect, ksize[0] as usize, ksize[1] as usize)
        .ok_or_else(|| "`ksize` must be at least 1".to_string())?;
    Ok((element, border))
}

/// Minimum filter (`filter.min`). See [`min_filter`].
#[derive(Debug, Clone, PartialEq)]
pub struct MinFilter {
    element: StructuringElement,
    border: MorphBorder,
}

/// Maximum filter (`filter.max`). See [`max_filter`].
#[derive(Debug, Clone, PartialEq)]
pub struct MaxFilter {
    element: StructuringElement,
    border: MorphBorder,
}

fn image_port(doc: &str) -> Vec<PortSpec> {
    vec![PortSpec::new("image", PortType::Image, doc)]
}

const INPUT_DOC: &str = "Image to filter, any pixel format (channels are filtered independently).";
const OUTPUT_DOC: &str = "The filtered image, same size and pixel format as the input.";

impl Op for MinFilter {
    type Params = RankParams;
    const ID: &'static str = "filter.min";
    const SUMMARY: &'static str = "The minimum of every rectangular window of an image.";
    const DOC: &'static str = r#"
Replaces every sample by the minimum of the `ksize[0] × ksize[1]` window around it, per channel
(anchor at ⌊ksize/2⌋ as OpenCV). Identical to `filter.erode` with shape "rect" and one
iteration, and to OpenCV's `cv::erode` with a rectangular `getStructuringElement`. Works on every
pixel format; the output has the input's format. Exact (no arithmetic).

Method: separable van Herk / Gil-Werman running minima (rows, then columns), three comparisons
per sample whatever the window size; small windows take the minimum of shifted rows directly.

References: M. van Herk, Pattern Recognition Letters 13(7), 1992; J. Gil and M. Werman, IEEE
PAMI 15(5), 1993; OpenCV `cv::erode`.

Example:
    "floor": (op: "filter.min", inputs: { "image": "card.image" }, params: (ksize: [5, 3])),
"#;

    fn inputs() -> Vec<PortSpec> {
        image_port(INPUT_DOC)
    }

    fn outputs() -> Vec<PortSpec> {
        image_port(OUTPUT_DOC)
    }

    fn new(params: RankParams) -> Result<Self, String> {
        let (element, border) = window(params)?;
        Ok(MinFilter { element, border })
    }
}

impl Op for MaxFilter {
    type Params = RankParams;
    const ID: &'static str = "filter.max";
    const SUMMARY: &'static str = "The maximum of every rectangular window of an image.";
    const DOC: &'static str = r#"
Replaces every sample by the maximum of the `ksize[0] × ksize[1]` window around it, per channel
(anchor at ⌊ksize/2⌋ as OpenCV). Identical to `filter.dilate` with shape "rect" and one
iteration, and to OpenCV's `cv::dilate` with a rectangular `getStructuringElement`. Works on
every pixel format; the output has the input's format. Exact (no arithmetic).

Method: separable van Herk / Gil-Werman running maxima (rows, then columns), three comparisons
per sample whatever the window size; small windows take the maximum of shifted rows directly.

References: M. van Herk, Pattern Recognition Letters 13(7), 1992; J. Gil and M. Werman, IEEE
PAMI 15(5), 1993; OpenCV `cv::dilate`.

Example:
    "ceiling": (op: "filter.max", inputs: { "image": "card.image" }, params: (ksize: [5, 5])),
"#;

    fn inputs() -> Vec<PortSpec> {
        image_port(INPUT_DOC)
    }

    fn outputs() -> Vec<PortSpec> {
        image_port(OUTPUT_DOC)
    }

    fn new(params: RankParams) -> Result<Self, String> {
        let (element, border) = window(params)?;
        Ok(MaxFilter { element, border })
    }
}

impl Operator for MinFilter {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = erode(image, &self.element, 1, self.border);
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

impl Operator for MaxFilter {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = dilate(image, &self.element, 1, self.border);
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// Minimum of every `width × height` window of `image` (anchor `⌊size/2⌋`), per channel; `None`
/// for a zero size.
pub fn min_filter(
    image: &Image,
    width: usize,
    height: usize,
    border: MorphBorder,
) -> Option<Image> {
    let element = StructuringElement::new(Shape::Rect, width, height)?;
    Some(erode(image, &element, 1, border))
}

/// Maximum of every `width × height` window of `image` (anchor `⌊size/2⌋`), per channel; `None`
/// for a zero size.
pub fn max_filter(
    image: &Image,
    width: usize,
    height: usize,
    border: MorphBorder,
) -> Option<Image> {
    let element = StructuringElement::new(Shape::Rect, width, height)?;
    Some(dilate(image, &element, 1, border))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::morphology::{Dilate, Erode, MorphParams};
    use crate::filter::test_support::random_u8;
    use ocellus_engine::value::Channels;

    fn run(op: &dyn Operator, img: &Image) -> Image {
        let specs = MinFilter::inputs();
        let values = [Some(Value::image(img.clone()))];
        let ctx = RunContext {
            node: "r".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        match out.take("image") {
            Some(Value::Image(got)) => (*got).clone(),
            _ => panic!("expected an image"),
        }
    }

    #[test]
    fn hand_computed_row() {
        let img = Image::from_u8(5, 1, Channels::Gray, vec![4, 1, 7, 3, 9]).unwrap();
        let lo = min_filter(&img, 3, 1, MorphBorder::Neutral).unwrap();
        let hi = max_filter(&img, 3, 1, MorphBorder::Neutral).unwrap();
        assert_eq!(lo.as_u8().unwrap(), &[1, 1, 1, 3, 3]);
        assert_eq!(hi.as_u8().unwrap(), &[4, 7, 7, 9, 9]);
        // Even width: the window of x starts at x − 1 and covers x − 1 ..= x.
        let lo = min_filter(&img, 2, 1, MorphBorder::Clamp).unwrap();
        assert_eq!(lo.as_u8().unwrap(), &[4, 1, 1, 3, 3]);
    }

    #[test]
    fn equal_erode_and_dilate_with_a_rectangle() {
        let img = random_u8(37, 23, Channels::Rgb, 9);
        for (ksize, border) in [
            ([3, 3], MorphBorder::Neutral),
            ([5, 2], MorphBorder::Reflect101),
            ([1, 9], MorphBorder::Clamp),
            ([12, 7], MorphBorder::Wrap),
        ] {
            let params = RankParams { ksize, border };
            let morph = MorphParams {
                ksize,
                border,
                ..MorphParams::default()
            };
            assert_eq!(
                run(&MinFilter::new(params.clone()).unwrap(), &img),
                run(&Erode::new(morph.clone()).unwrap(), &img)
            );
            assert_eq!(
                run(&MaxFilter::new(params).unwrap(), &img),
                run(&Dilate::new(morph).unwrap(), &img)
            );
        }
    }

    #[test]
    fn params_are_checked_and_tiny_images_work() {
        let bad = RankParams {
            ksize: [0, 3],
            ..RankParams::default()
        };
        assert!(MinFilter::new(bad).unwrap_err().contains("width"));
        let bad = RankParams {
            ksize: [3, 1024],
            ..RankParams::default()
        };
        assert!(MaxFilter::new(bad).unwrap_err().contains("height"));
        let one = Image::from_u8(1, 1, Channels::Gray, vec![7]).unwrap();
        assert_eq!(min_filter(&one, 5, 5, MorphBorder::Neutral).unwrap(), one);
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        assert_eq!(max_filter(&empty, 3, 3, MorphBorder::Clamp).unwrap(), empty);
        assert!(min_filter(&one, 0, 3, MorphBorder::Clamp).is_none());
    }
}
