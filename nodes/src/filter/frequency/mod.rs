//! Frequency-domain operators: the 2-D discrete Fourier transform and its inverse
//! ([`fft`]), low/high-pass filtering in the Fourier domain ([`pass`]), the 8×8 blockwise
//! DCT of JPEG ([`dct`]) and the multi-level Haar wavelet transform ([`haar`]).
//!
//! There is no complex image type: a spectrum is a pair of f32 images, `real` and `imaginary`,
//! with the channels of the transformed image. Every operator here works on each channel of
//! its input on its own and outputs f32.

pub mod dct;
pub mod fft;
pub mod haar;
pub mod pass;

use ocellus_engine::op::OpError;
use ocellus_engine::value::{Channels, Image, PixelData, ValueError};
use rayon::prelude::*;

/// Samples per parallel task when converting between interleaved images and planes.
const CONVERT_CHUNK: usize = 1 << 16;

/// The channels of `image` as separate f32 planes of `width × height` samples (u8 and u16
/// values are converted as they are, without scaling).
pub fn to_planes(image: &Image) -> Vec<Vec<f32>> {
    let channels = image.channels().count();
    let n = image.width() * image.height();
    (0..channels)
        .map(|c| match image.data() {
            PixelData::U8(v) => extract(v, channels, c, n, f32::from),
            PixelData::U16(v) => extract(v, channels, c, n, f32::from),
            PixelData::F32(v) => extract(v, channels, c, n, |x| x),
        })
        .collect()
}

fn extract<T: Copy + Sync>(
    data: &[T],
    channels: usize,
    channel: usize,
    n: usize,
    convert: impl Fn(T) -> f32 + Sync,
) -> Vec<f32> {
    let mut plane = vec![0.0f32; n];
    if channels == 1 {
        plane
            .par_chunks_mut(CONVERT_CHUNK)
            .zip(data.par_chunks(CONVERT_CHUNK))
            .for_each(|(dst, src)| {
                for (d, &s) in dst.iter_mut().zip(src) {
                    *d = convert(s);
                }
            });
    } else {
        plane
            .par_chunks_mut(CONVERT_CHUNK)
            .zip(data.par_chunks(CONVERT_CHUNK * channels))
            .for_each(|(dst, src)| {
                for (d, px) in dst.iter_mut().zip(src.chunks_exact(channels)) {
                    *d = convert(px[channel]);
                }
            });
    }
    plane
}

/// An f32 image of `width × height` with one channel per plane (1, 3 or 4 planes of
/// `width × height` samples), interleaving them.
pub fn from_planes(
    width: usize,
    height: usize,
    channels: Channels,
    planes: Vec<Vec<f32>>,
) -> Result<Image, ValueError> {
    let count = channels.count();
    let data = if count == 1 {
        planes.into_iter().next().unwrap_or_default()
    } else {
        let mut data = vec![0.0f32; width * height * count];
        data.par_chunks_mut(CONVERT_CHUNK * count)
            .enumerate()
            .for_each(|(i, dst)| {
                let start = i * CONVERT_CHUNK;
                for (c, plane) in planes.iter().enumerate() {
                    let Some(src) = plane.get(start..start + dst.len() / count) else {
                        continue;
                    };
                    for (px, &s) in dst.chunks_exact_mut(count).zip(src) {
                        px[c] = s;
                    }
                }
            });
        data
    };
    Image::from_f32(width, height, channels, data)
}

/// [`from_planes`] for operators: a size mismatch (a bug) becomes an [`OpError`].
pub(crate) fn planes_image(
    width: usize,
    height: usize,
    channels: Channels,
    planes: Vec<Vec<f32>>,
) -> Result<Image, OpError> {
    from_planes(width, height, channels, planes).map_err(|e| OpError::failed(e.to_string()))
}
