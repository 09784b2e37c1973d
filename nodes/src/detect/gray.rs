//! Gray 8-bit views of any input image, shared by the detectors that work on intensities
//! (`detect.mser`, `detect.qr_finder`, `detect.chessboard`, `detect.aruco`).
//!
//! Conversion rules (documented in each operator's DOC):
//! - gray u8: used as is;
//! - u16: `round(v / 257)` (0–65535 onto 0–255);
//! - f32: `round(clamp(v, 0, 1) · 255)`, NaN read as 0;
//! - RGB / RGBA: BT.601 luma with OpenCV's `RGB2GRAY` fixed point, `(4899 R + 9617 G + 1868 B +
//!   2^13) >> 14`, after the per-sample conversion above; alpha is ignored.

use std::borrow::Cow;

use ocellus_engine::value::{Channels, Image, PixelData};

/// 8-bit sample of a 16-bit one.
#[inline]
fn from_u16(v: u16) -> u8 {
    ((u32::from(v) + 128) / 257) as u8
}

/// 8-bit sample of a float one (0–1 range; NaN becomes 0).
#[inline]
fn from_f32(v: f32) -> u8 {
    let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
    (v * 255.0).round() as u8
}

/// Luma of three 8-bit samples (OpenCV's fixed point).
#[inline]
fn luma(r: u8, g: u8, b: u8) -> u8 {
    ((4899 * u32::from(r) + 9617 * u32::from(g) + 1868 * u32::from(b) + (1 << 13)) >> 14) as u8
}

/// Gray 8-bit samples of `image`, `width × height`, row-major; borrowed for gray u8.
pub fn gray_u8(image: &Image) -> Cow<'_, [u8]> {
    let c = image.channels().count();
    let convert = |samples: Vec<u8>| -> Vec<u8> {
        if c == 1 {
            samples
        } else {
            samples
                .chunks_exact(c)
                .map(|p| luma(p[0], p[1], p[2]))
                .collect()
        }
    };
    match image.data() {
        PixelData::U8(v) if image.channels() == Channels::Gray => Cow::Borrowed(v.as_slice()),
        PixelData::U8(v) => Cow::Owned(convert(v.clone())),
        PixelData::U16(v) => Cow::Owned(convert(v.iter().map(|&s| from_u16(s)).collect())),
        PixelData::F32(v) => Cow::Owned(convert(v.iter().map(|&s| from_f32(s)).collect())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn conversions() {
        let g = Image::from_u8(2, 1, Channels::Gray, vec![3, 250]).unwrap();
        assert!(matches!(gray_u8(&g), Cow::Borrowed(_)));
        let w = Image::from_u16(2, 1, Channels::Gray, vec![65535, 257 * 10]).unwrap();
        assert_eq!(&*gray_u8(&w), &[255, 10]);
        let f = Image::from_f32(3, 1, Channels::Gray, vec![2.0, f32::NAN, 0.5]).unwrap();
        assert_eq!(&*gray_u8(&f), &[255, 0, 128]);
        let rgb = Image::from_u8(1, 1, Channels::Rgb, vec![255, 255, 255]).unwrap();
        assert_eq!(&*gray_u8(&rgb), &[255]);
        let rgba = Image::from_u8(1, 1, Channels::Rgba, vec![100, 100, 100, 0]).unwrap();
        assert_eq!(&*gray_u8(&rgba), &[100]);
    }
}
