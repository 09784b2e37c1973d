//! OpenEXR reading and writing, for f32 images (depth maps, HDR renders, flow fields).
//!
//! Built on the pure-Rust `exr` crate. Only the first layer's largest resolution level is read;
//! the pixels of its data window become the image (the display window and metadata are not
//! kept). Channels map to layouts as follows:
//!
//! | channels in the file            | becomes        |
//! |---------------------------------|----------------|
//! | exactly one (any name: Y, Z, …) | `gray_f32`     |
//! | R, G, B                         | `rgb_f32`      |
//! | R, G, B, A                      | `rgba_f32`     |
//!
//! Half-float and u32 samples are widened to f32. Writing stores gray as a `Y` channel and
//! colour as `R`, `G`, `B` (`A`), f32, ZIP-compressed (lossless); u8/u16 images must be
//! converted first (the scale is the caller's choice).

use std::io::Cursor;
use std::path::Path;

use exr::prelude::{
    AnyChannel, AnyChannels, Encoding, FlatSamples, Image as ExrImage, Layer, LayerAttributes,
    MetaData, ReadChannels, ReadLayers, SmallVec, WritableImage,
};

use crate::image_io::{DecodeLimits, ImageIoError, Limit};
use crate::value::{Channels, Image, PixelData};

/// The four bytes every OpenEXR file starts with.
pub(crate) const EXR_MAGIC: [u8; 4] = [0x76, 0x2f, 0x31, 0x01];

/// Decodes an OpenEXR file held in memory. The header's dimensions are checked against
/// `limits` before any pixel buffer is allocated.
pub(crate) fn decode_exr(
    bytes: &[u8],
    path: &Path,
    limits: &DecodeLimits,
) -> Result<Image, ImageIoError> {
    let corrupt = |message: String| ImageIoError::Corrupt {
        path: path.to_path_buf(),
        message: format!("EXR: {message}"),
    };
    let meta = MetaData::read_from_buffered(Cursor::new(bytes), false)
        .map_err(|e| corrupt(e.to_string()))?;
    let header = meta
        .headers
        .first()
        .ok_or_else(|| corrupt("the file has no layer".into()))?;
    let size = header.layer_size;
    let (width, height) = (size.width() as u64, size.height() as u64);
    let channel_count = header.channels.list.len() as u64;
    let too_large = |limit| ImageIoError::TooLarge {
        path: path.to_path_buf(),
        width,
        height,
        limit,
    };
    let pixels = width
        .checked_mul(height)
        .ok_or_else(|| too_large(Limit::Pixels(limits.max_pixels)))?;
    if pixels > limits.max_pixels {
        return Err(too_large(Limit::Pixels(limits.max_pixels)));
    }
    match pixels.checked_mul(channel_count.max(1) * 4) {
        Some(bytes) if bytes <= limits.max_alloc_bytes => {}
        _ => return Err(too_large(Limit::Bytes(limits.max_alloc_bytes))),
    }
    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(Cursor::new(bytes))
        .map_err(|e| corrupt(e.to_string()))?;
    let layer = image.layer_data;
    let (w, h) = (layer.size.width(), layer.size.height());
    let list = &layer.channel_data.list;
    let find = |name: &str| list.iter().find(|c| c.name.to_string() == name);
    let as_f32 =
        |c: &AnyChannel<FlatSamples>| -> Vec<f32> { c.sample_data.values_as_f32().collect() };
    let (channels, planes): (Channels, Vec<Vec<f32>>) = if list.len() == 1 {
        (Channels::Gray, vec![as_f32(&list[0])])
    } else {
        match (find("R"), find("G"), find("B"), find("A")) {
            (Some(r), Some(g), Some(b), None) => {
                (Channels::Rgb, vec![as_f32(r), as_f32(g), as_f32(b)])
            }
            (Some(r), Some(g), Some(b), Some(a)) => (
                Channels::Rgba,
                vec![as_f32(r), as_f32(g), as_f32(b), as_f32(a)],
            ),
            _ => {
                let names: Vec<String> = list.iter().map(|c| c.name.to_string()).collect();
                return Err(ImageIoError::Unsupported {
                    path: path.to_path_buf(),
                    message: format!(
                        "EXR channels [{}] are neither one channel nor R, G, B (A)",
                        names.join(", ")
                    ),
                });
            }
        }
    };
    let count = channels.count();
    if planes.iter().any(|p| p.len() != w * h) {
        return Err(corrupt("a channel has the wrong number of samples".into()));
    }
    let mut samples = vec![0.0f32; w * h * count];
    for (c, plane) in planes.iter().enumerate() {
        for (dst, &src) in samples.iter_mut().skip(c).step_by(count).zip(plane) {
            *dst = src;
        }
    }
    Image::new(w, h, channels, PixelData::F32(samples)).map_err(|e| corrupt(e.to_string()))
}

/// Encodes an f32 image as OpenEXR (see the module docs for the channel names).
pub(crate) fn encode_exr(image: &Image) -> Result<Vec<u8>, ImageIoError> {
    let unsupported = |message: String| ImageIoError::Unsupported {
        path: Default::default(),
        message,
    };
    let Some(samples) = image.as_f32() else {
        return Err(unsupported(format!(
            "EXR stores f32 samples here, not {}; convert first (filter.convert_type)",
            image.depth().name()
        )));
    };
    let names: &[&str] = match image.channels() {
        Channels::Gray => &["Y"],
        Channels::Rgb => &["R", "G", "B"],
        Channels::Rgba => &["R", "G", "B", "A"],
    };
    let count = names.len();
    let channels: SmallVec<[AnyChannel<FlatSamples>; 4]> = names
        .iter()
        .enumerate()
        .map(|(c, name)| {
            let plane: Vec<f32> = samples.iter().skip(c).step_by(count).copied().collect();
            AnyChannel::new(*name, FlatSamples::F32(plane))
        })
        .collect();
    let layer = Layer::new(
        (image.width(), image.height()),
        LayerAttributes::default(),
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(channels),
    );
    let mut out = Cursor::new(Vec::new());
    ExrImage::from_layer(layer)
        .write()
        .non_parallel()
        .to_buffered(&mut out)
        .map_err(|e| unsupported(format!("EXR encoding failed: {e}")))?;
    Ok(out.into_inner())
}
