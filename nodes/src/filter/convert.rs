//! `filter.convert_type`, `filter.split_channels` and `filter.merge_channels`: sample-type
//! conversion and channel (de)interleaving.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Depth, Image, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

/// Samples per parallel task.
const SAMPLES_PER_TASK: usize = 1 << 16;

param_enum! {
    /// Output sample type.
    pub enum SampleType {
        /// 8-bit unsigned.
        U8 = "u8",
        /// 16-bit unsigned.
        U16 = "u16",
        /// 32-bit float.
        F32 = "f32",
    }
}

impl SampleType {
    /// The engine's depth.
    pub fn depth(self) -> Depth {
        match self {
            SampleType::U8 => Depth::U8,
            SampleType::U16 => Depth::U16,
            SampleType::F32 => Depth::F32,
        }
    }
}

/// The value of full scale of a depth: 255, 65535 or 1.
fn full_scale(depth: Depth) -> f64 {
    match depth {
        Depth::U8 => 255.0,
        Depth::U16 => 65535.0,
        Depth::F32 => 1.0,
    }
}

/// The scale that maps `from`'s full range onto `to`'s (×1/255 for u8 → f32, ×257 for
/// u8 → u16, …; 1 for the same depth).
pub fn full_range_scale(from: Depth, to: Depth) -> f64 {
    full_scale(to) / full_scale(from)
}

params! {
    /// Parameters of `filter.convert_type`.
    pub struct ConvertTypeParams {
        /// Output sample type: "u8", "u16" or "f32". Default "f32".
        depth: SampleType = SampleType::F32,
        /// Factor applied to every sample (output units per input unit). None (the default) maps
        /// full range to full range: u8 → f32 ×1/255, f32 → u8 ×255, u8 → u16 ×257,
        /// u16 → u8 ×1/257, u16 → f32 ×1/65535, f32 → u16 ×65535, same type ×1.
        scale: Option<f64> = None,
        /// Value added after scaling, in output units. Default 0.
        offset: f64 = 0.0,
    }
}

/// Sample-type conversion (`filter.convert_type`). See [`convert_type`].
#[derive(Debug, Clone, PartialEq)]
pub struct ConvertType {
    depth: Depth,
    scale: Option<f64>,
    offset: f64,
}

impl Op for ConvertType {
    type Params = ConvertTypeParams;
    const ID: &'static str = "filter.convert_type";
    const SUMMARY: &'static str =
        "Converts samples to u8, u16 or f32 with an optional scale and offset.";
    const DOC: &'static str = r#"
Converts every sample: out = in · scale + offset, computed in f64. Integer outputs are
rounded to nearest with ties to even and saturated to the type's range (NaN gives 0), as
OpenCV's `Mat::convertTo` (`saturate_cast` rounds with `cvRound`, ties to even: 2.5 → 2,
3.5 → 4). f32 output is the plain result rounded to f32. Channels are unchanged.

Unlike `convertTo`, whose scale defaults to 1, the default scale maps full range to full
range (u8 0..255 ↔ u16 0..65535 ↔ f32 0..1): u8 → f32 multiplies by 1/255, u8 → u16 by 257
(exact: 255 → 65535), u16 → u8 by 1/257. Give `scale: 1.0` for OpenCV's behaviour.

u8 and u16 inputs to u8 or u16 go through a table of every input value (one lookup per
sample whatever the scale); conversions to f32 are plain vectorized arithmetic.

Reference: OpenCV `cv::Mat::convertTo`.

Example:
    "unit": (op: "filter.convert_type", inputs: { "image": "photo.image" }, params: (depth: "f32")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to convert: any channels, any sample type.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Same size and channels, samples of type `depth`.",
        )]
    }

    fn new(params: ConvertTypeParams) -> Result<Self, String> {
        if let Some(scale) = params.scale
            && !scale.is_finite()
        {
            return Err(format!("`scale` must be finite, got {scale}"));
        }
        if !params.offset.is_finite() {
            return Err(format!("`offset` must be finite, got {}", params.offset));
        }
        Ok(ConvertType {
            depth: params.depth.depth(),
            scale: params.scale,
            offset: params.offset,
        })
    }
}

impl Operator for ConvertType {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = convert_type(image, self.depth, self.scale, self.offset)
            .map_err(|e| OpError::failed(format!("converting the samples: {e}")))?;
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// A sample type the conversion writes.
trait Sample: Copy + Default + Send + Sync {
    /// Rounds (ties to even) and saturates an f64 (integers; NaN → 0), or narrows it (f32).
    fn from_f64(x: f64) -> Self;
}

impl Sample for u8 {
    #[inline]
    fn from_f64(x: f64) -> Self {
        x.round_ties_even() as u8
    }
}

impl Sample for u16 {
    #[inline]
    fn from_f64(x: f64) -> Self {
        x.round_ties_even() as u16
    }
}

impl Sample for f32 {
    #[inline]
    fn from_f64(x: f64) -> Self {
        x as f32
    }
}

/// `saturate(round(in · scale + offset))` for every sample, into `depth`; `scale` None maps
/// full range to full range ([`full_range_scale`]).
pub fn convert_type(
    image: &Image,
    depth: Depth,
    scale: Option<f64>,
    offset: f64,
) -> Result<Image, ocellus_engine::value::ValueError> {
    let scale = scale.unwrap_or_else(|| full_range_scale(image.depth(), depth));
    let data = match image.data() {
        PixelData::U8(src) => match depth {
            Depth::U8 => PixelData::U8(by_table(src, scale, offset)),
            Depth::U16 => PixelData::U16(by_table(src, scale, offset)),
            Depth::F32 => PixelData::F32(integer_to_float(src, scale, offset)),
        },
        PixelData::U16(src) => match depth {
            Depth::U8 => PixelData::U8(by_table(src, scale, offset)),
            Depth::U16 => PixelData::U16(by_table(src, scale, offset)),
            Depth::F32 => PixelData::F32(integer_to_float(src, scale, offset)),
        },
        PixelData::F32(src) => match depth {
            Depth::U8 => PixelData::U8(from_float(src, scale, offset)),
            Depth::U16 => PixelData::U16(from_float(src, scale, offset)),
            Depth::F32 => PixelData::F32(from_float(src, scale, offset)),
        },
    };
    Image::new(image.width(), image.height(), image.channels(), data)
}

/// Integer inputs: a table of every input value's result, then one lookup per sample.
fn by_table<T, O>(src: &[T], scale: f64, offset: f64) -> Vec<O>
where
    T: Copy + Sync + Into<usize> + TableIndex,
    O: Sample,
{
    let table: Vec<O> = (0..T::VALUES)
        .map(|v| O::from_f64(v as f64 * scale + offset))
        .collect();
    let mut dst = ocellus_engine::buffer::zeroed::<O>(src.len());
    dst.par_chunks_mut(SAMPLES_PER_TASK)
        .zip(src.par_chunks(SAMPLES_PER_TASK))
        .for_each(|(out, inp)| {
            for (o, &v) in out.iter_mut().zip(inp) {
                if let Some(&t) = table.get(v.into()) {
                    *o = t;
                }
            }
        });
    dst
}

/// Integer inputs to f32: plain arithmetic, which vectorizes (a table lookup does not).
fn integer_to_float<T: Copy + Sync + Into<f64>>(src: &[T], scale: f64, offset: f64) -> Vec<f32> {
    let mut dst = vec![0.0; src.len()];
    dst.par_chunks_mut(SAMPLES_PER_TASK)
        .zip(src.par_chunks(SAMPLES_PER_TASK))
        .for_each(|(out, inp)| {
            for (o, &v) in out.iter_mut().zip(inp) {
                *o = (v.into() * scale + offset) as f32;
            }
        });
    dst
}

/// Number of values of an integer sample type.
trait TableIndex {
    /// 256 or 65536.
    const VALUES: usize;
}

impl TableIndex for u8 {
    const VALUES: usize = 256;
}

impl TableIndex for u16 {
    const VALUES: usize = 65536;
}

fn from_float<O: Sample>(src: &[f32], scale: f64, offset: f64) -> Vec<O> {
    let mut dst = ocellus_engine::buffer::zeroed::<O>(src.len());
    dst.par_chunks_mut(SAMPLES_PER_TASK)
        .zip(src.par_chunks(SAMPLES_PER_TASK))
        .for_each(|(out, inp)| {
            for (o, &v) in out.iter_mut().zip(inp) {
                *o = O::from_f64(f64::from(v) * scale + offset);
            }
        });
    dst
}

// ---------------------------------------------------------------------------------------------
// Channels

/// Channel splitting (`filter.split_channels`). See [`split_channels`].
#[derive(Debug, Clone, PartialEq)]
pub struct SplitChannels;

impl Op for SplitChannels {
    type Params = ocellus_engine::params::NoParams;
    const ID: &'static str = "filter.split_channels";
    const SUMMARY: &'static str = "Splits an image into one gray image per channel.";
    const DOC: &'static str = r#"
Splits an image into a list of one-channel (gray) images of the same size and sample type, in
channel order: [R, G, B] for RGB, [R, G, B, A] for RGBA, [Y] for gray. Samples are copied
unchanged. `filter.merge_channels` is the inverse.

Reference: OpenCV `cv::split`.

Example:
    "planes": (op: "filter.split_channels", inputs: { "image": "photo.image" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to split: any channels, any sample type.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "channels",
            PortType::Image.list_of(),
            "One gray image per channel, in channel order.",
        )]
    }

    fn new(_: ocellus_engine::params::NoParams) -> Result<Self, String> {
        Ok(SplitChannels)
    }
}

impl Operator for SplitChannels {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let planes = split_channels(image)
            .map_err(|e| OpError::failed(format!("splitting channels: {e}")))?;
        let items = planes.into_iter().map(Value::image).collect();
        Ok(Outputs::new().with("channels", Value::list(PortType::Image, items)))
    }
}

fn deinterleave<T: Copy + Default>(src: &[T], c: usize) -> Vec<Vec<T>> {
    (0..c)
        .map(|k| src.iter().skip(k).step_by(c).copied().collect())
        .collect()
}

/// One gray image per channel of `image`, in channel order.
pub fn split_channels(image: &Image) -> Result<Vec<Image>, ocellus_engine::value::ValueError> {
    let c = image.channels().count();
    let (w, h) = (image.width(), image.height());
    let planes: Vec<PixelData> = match image.data() {
        PixelData::U8(v) => deinterleave(v, c).into_iter().map(PixelData::U8).collect(),
        PixelData::U16(v) => deinterleave(v, c).into_iter().map(PixelData::U16).collect(),
        PixelData::F32(v) => deinterleave(v, c).into_iter().map(PixelData::F32).collect(),
    };
    planes
        .into_iter()
        .map(|data| Image::new(w, h, Channels::Gray, data))
        .collect()
}

/// Channel merging (`filter.merge_channels`). See [`merge_channels`].
#[derive(Debug, Clone, PartialEq)]
pub struct MergeChannels;

impl Op for MergeChannels {
    type Params = ocellus_engine::params::NoParams;
    const ID: &'static str = "filter.merge_channels";
    const SUMMARY: &'static str = "Merges 1, 3 or 4 gray images into a gray, RGB or RGBA image.";
    const DOC: &'static str = r#"
Interleaves a list of one-channel images into one image: 1 image gives gray, 3 give RGB,
4 give RGBA, in list order. All must be gray, of one size and one sample type (otherwise the
error names the first that differs). The port takes the whole list (a `List<Image>` port is
not mapped over its elements). `filter.split_channels` is the inverse.

Reference: OpenCV `cv::merge`.

Example:
    "rgb": (op: "filter.merge_channels", inputs: { "channels": "planes.channels" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "channels",
            PortType::Image.list_of(),
            "1, 3 or 4 gray images of equal size and sample type.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Gray, RGB or RGBA image of the same size and sample type.",
        )]
    }

    fn new(_: ocellus_engine::params::NoParams) -> Result<Self, String> {
        Ok(MergeChannels)
    }
}

impl Operator for MergeChannels {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let list = match inputs.require("channels")? {
            Value::List(list) => list,
            other => {
                return Err(OpError::input(
                    "channels",
                    format!("expected List<Image>, got {}", other.port_type()),
                ));
            }
        };
        let mut planes = Vec::with_capacity(list.items.len());
        for (k, item) in list.items.iter().enumerate() {
            match item {
                Value::Image(image) => planes.push(image.as_ref()),
                other => {
                    return Err(OpError::input(
                        "channels",
                        format!("element {k} is a {}, not an Image", other.port_type()),
                    ));
                }
            }
        }
        let image = merge_channels(&planes).map_err(|e| OpError::input("channels", e))?;
        Ok(Outputs::new().with("image", Value::image(image)))
    }
}

fn interleave<T: Copy + Default>(planes: &[&[T]]) -> Vec<T> {
    let c = planes.len();
    let n = planes.first().map_or(0, |p| p.len());
    let mut out = ocellus_engine::buffer::zeroed::<T>(n * c);
    for (k, plane) in planes.iter().enumerate() {
        for (o, &v) in out.iter_mut().skip(k).step_by(c).zip(plane.iter()) {
            *o = v;
        }
    }
    out
}

/// Interleaves 1, 3 or 4 gray images of equal size and sample type into gray, RGB or RGBA.
pub fn merge_channels(planes: &[&Image]) -> Result<Image, String> {
    let channels = match planes.len() {
        1 => Channels::Gray,
        3 => Channels::Rgb,
        4 => Channels::Rgba,
        n => return Err(format!("needs 1, 3 or 4 images, got {n}")),
    };
    let first = planes[0];
    for (k, p) in planes.iter().enumerate() {
        if p.channels() != Channels::Gray {
            return Err(format!(
                "element {k} has {} channels; every element must be gray",
                p.channels().name()
            ));
        }
        if (p.width(), p.height()) != (first.width(), first.height()) {
            return Err(format!(
                "element {k} is {}×{}, element 0 is {}×{}",
                p.width(),
                p.height(),
                first.width(),
                first.height()
            ));
        }
        if p.depth() != first.depth() {
            return Err(format!(
                "element {k} has {} samples, element 0 has {}",
                p.depth().name(),
                first.depth().name()
            ));
        }
    }
    let data = match first.depth() {
        Depth::U8 => {
            let v: Vec<&[u8]> = planes.iter().filter_map(|p| p.as_u8()).collect();
            PixelData::U8(interleave(&v))
        }
        Depth::U16 => {
            let v: Vec<&[u16]> = planes.iter().filter_map(|p| p.as_u16()).collect();
            PixelData::U16(interleave(&v))
        }
        Depth::F32 => {
            let v: Vec<&[f32]> = planes.iter().filter_map(|p| p.as_f32()).collect();
            PixelData::F32(interleave(&v))
        }
    };
    Image::new(first.width(), first.height(), channels, data).map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::{random_u8, randoms};
    use proptest::prelude::*;

    fn ctx() -> RunContext {
        RunContext {
            node: "n".into(),
            threads: 1,
            element: None,
        }
    }

    #[test]
    fn rounds_half_to_even_and_saturates_like_opencv() {
        // OpenCV 5.0 convertScaleAbs / convertTo to u8: [0.5, 1.5, 2.5, 3.5, −0.5, 254.5,
        // 255.5] → [0, 2, 2, 4, 0, 254, 255].
        let img = Image::from_f32(
            8,
            1,
            Channels::Gray,
            vec![0.5, 1.5, 2.5, 3.5, -0.5, 254.5, 255.5, f32::NAN],
        )
        .unwrap();
        let out = convert_type(&img, Depth::U8, Some(1.0), 0.0).unwrap();
        assert_eq!(out.as_u8().unwrap(), [0, 2, 2, 4, 0, 254, 255, 0]);
        let out = convert_type(&img, Depth::U16, Some(1.0), 0.0).unwrap();
        assert_eq!(out.as_u16().unwrap(), [0, 2, 2, 4, 0, 254, 256, 0]);
    }

    #[test]
    fn default_scales_map_full_range() {
        let img = Image::from_u8(3, 1, Channels::Gray, vec![0, 128, 255]).unwrap();
        let f = convert_type(&img, Depth::F32, None, 0.0).unwrap();
        assert_eq!(f.as_f32().unwrap(), [0.0, (128.0f64 / 255.0) as f32, 1.0]);
        let w = convert_type(&img, Depth::U16, None, 0.0).unwrap();
        assert_eq!(w.as_u16().unwrap(), [0, 128 * 257, 65535]);
        let back = convert_type(&w, Depth::U8, None, 0.0).unwrap();
        assert_eq!(back, img);
        let back = convert_type(&f, Depth::U8, None, 0.0).unwrap();
        assert_eq!(back, img);
        let same = convert_type(&img, Depth::U8, None, 0.0).unwrap();
        assert_eq!(same, img);
        assert_eq!(full_range_scale(Depth::U16, Depth::F32), 1.0 / 65535.0);
        assert_eq!(full_range_scale(Depth::F32, Depth::U16), 65535.0);
    }

    #[test]
    fn scale_and_offset() {
        let img = Image::from_u16(2, 1, Channels::Gray, vec![10, 1000]).unwrap();
        // 10·0.5 − 3 = 2; 1000·0.5 − 3 = 497 → saturates to 255.
        let out = convert_type(&img, Depth::U8, Some(0.5), -3.0).unwrap();
        assert_eq!(out.as_u8().unwrap(), [2, 255]);
        let out = convert_type(&img, Depth::F32, Some(2.0), 0.25).unwrap();
        assert_eq!(out.as_f32().unwrap(), [20.25, 2000.25]);
        let rgba = random_u8(5, 3, Channels::Rgba, 1);
        let out = convert_type(&rgba, Depth::F32, Some(1.0), 0.0).unwrap();
        assert_eq!(out.channels(), Channels::Rgba);
        for (a, b) in out.as_f32().unwrap().iter().zip(rgba.as_u8().unwrap()) {
            assert_eq!(*a, f32::from(*b));
        }
    }

    #[test]
    fn new_rejects_non_finite_params() {
        let p = |scale, offset| ConvertTypeParams {
            depth: SampleType::U8,
            scale,
            offset,
        };
        assert!(ConvertType::new(p(None, 0.0)).is_ok());
        assert!(ConvertType::new(p(Some(f64::NAN), 0.0)).is_err());
        assert!(ConvertType::new(p(Some(f64::INFINITY), 0.0)).is_err());
        assert!(ConvertType::new(p(Some(2.0), f64::NAN)).is_err());
    }

    #[test]
    fn empty_and_operator() {
        let empty = Image::from_u8(0, 2, Channels::Rgb, vec![]).unwrap();
        let out = convert_type(&empty, Depth::F32, None, 0.0).unwrap();
        assert_eq!((out.width(), out.height(), out.depth()), (0, 2, Depth::F32));
        let op = ConvertType::new(ConvertTypeParams::default()).unwrap();
        let specs = ConvertType::inputs();
        let values = [Some(Value::image(
            Image::from_u8(1, 1, Channels::Gray, vec![255]).unwrap(),
        ))];
        let mut out = op.run(&ctx(), &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Image(img)) = out.take("image") else {
            panic!("expected an image");
        };
        assert_eq!(img.as_f32().unwrap(), [1.0]);
    }

    #[test]
    fn split_and_merge_by_hand() {
        let img = Image::from_u8(2, 1, Channels::Rgb, vec![1, 2, 3, 4, 5, 6]).unwrap();
        let planes = split_channels(&img).unwrap();
        assert_eq!(planes.len(), 3);
        assert_eq!(planes[0].as_u8().unwrap(), [1, 4]);
        assert_eq!(planes[2].as_u8().unwrap(), [3, 6]);
        let refs: Vec<&Image> = planes.iter().collect();
        assert_eq!(merge_channels(&refs).unwrap(), img);
        // Two planes, mixed sizes, mixed depths and colour elements are errors.
        assert!(
            merge_channels(&refs[..2])
                .unwrap_err()
                .contains("1, 3 or 4")
        );
        let small = Image::from_u8(1, 1, Channels::Gray, vec![0]).unwrap();
        let err = merge_channels(&[refs[0], &small, refs[2]]).unwrap_err();
        assert!(err.contains("element 1 is 1×1"), "{err}");
        let deep = Image::from_u16(2, 1, Channels::Gray, vec![0, 0]).unwrap();
        let err = merge_channels(&[refs[0], refs[1], &deep]).unwrap_err();
        assert!(err.contains("element 2 has u16"), "{err}");
        let err = merge_channels(&[&img]).unwrap_err();
        assert!(err.contains("must be gray"), "{err}");
        assert!(merge_channels(&[]).is_err());
    }

    #[test]
    fn operators_pass_lists() {
        let img = random_u8(4, 3, Channels::Rgba, 7);
        let specs = SplitChannels::inputs();
        let values = [Some(Value::image(img.clone()))];
        let mut out = SplitChannels
            .run(&ctx(), &Inputs::new(&specs, &values))
            .unwrap();
        let list = out.take("channels").unwrap();
        assert_eq!(list.port_type(), PortType::Image.list_of());
        let specs = MergeChannels::inputs();
        let values = [Some(list)];
        let mut out = MergeChannels
            .run(&ctx(), &Inputs::new(&specs, &values))
            .unwrap();
        assert_eq!(out.take("image"), Some(Value::image(img)));
        let values = [Some(Value::list(
            PortType::Scalar,
            vec![Value::Scalar(1.0)],
        ))];
        let err = MergeChannels
            .run(&ctx(), &Inputs::new(&specs, &values))
            .unwrap_err();
        assert!(err.to_string().contains("element 0 is a Scalar"), "{err}");
        let values = [Some(Value::Scalar(1.0))];
        assert!(
            MergeChannels
                .run(&ctx(), &Inputs::new(&specs, &values))
                .is_err()
        );
    }

    proptest! {
        #[test]
        fn u8_to_f32_to_u8_is_identity(v: Vec<u8>) {
            let img = Image::from_u8(v.len(), 1, Channels::Gray, v).unwrap();
            let f = convert_type(&img, Depth::F32, None, 0.0).unwrap();
            prop_assert_eq!(convert_type(&f, Depth::U8, None, 0.0).unwrap(), img);
        }

        #[test]
        fn matches_the_formula(x in -1000.0f32..1000.0, scale in -3.0f64..3.0, offset in -300.0f64..300.0) {
            let img = Image::from_f32(1, 1, Channels::Gray, vec![x]).unwrap();
            let y = f64::from(x) * scale + offset;
            let u = convert_type(&img, Depth::U8, Some(scale), offset).unwrap();
            prop_assert_eq!(f64::from(u.as_u8().unwrap()[0]), y.round_ties_even().clamp(0.0, 255.0));
            let w = convert_type(&img, Depth::U16, Some(scale), offset).unwrap();
            prop_assert_eq!(f64::from(w.as_u16().unwrap()[0]), y.round_ties_even().clamp(0.0, 65535.0));
        }

        #[test]
        fn split_merge_round_trip(w in 0usize..9, h in 0usize..9, c in prop::sample::select(vec![1usize, 3, 4]), seed: u64) {
            let channels = match c { 1 => Channels::Gray, 3 => Channels::Rgb, _ => Channels::Rgba };
            let data: Vec<f32> = randoms(seed, w * h * c).iter().map(|&x| x as f32).collect();
            let img = Image::from_f32(w, h, channels, data).unwrap();
            let planes = split_channels(&img).unwrap();
            prop_assert_eq!(planes.len(), c);
            let refs: Vec<&Image> = planes.iter().collect();
            prop_assert_eq!(merge_channels(&refs).unwrap(), img);
        }
    }
}
