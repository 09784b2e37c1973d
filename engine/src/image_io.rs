//! Reading and writing image files: PNG, JPEG, PNM (PGM/PPM/PAM), TIFF, PFM and OpenEXR.
//!
//! # Reading
//! [`read_image`] and [`decode_image`] pick the format from the file's content (magic bytes) and
//! fall back to the extension only when the content is not recognised. Samples are mapped to an
//! [`Image`] without lossy conversion:
//!
//! | stored as                      | becomes                         |
//! |--------------------------------|---------------------------------|
//! | gray, rgb, rgba (8 / 16 bit)   | the same layout, `u8` / `u16`   |
//! | gray + alpha (8 / 16 bit)      | `rgba`, gray copied to r, g, b  |
//! | palette / 1-bit (PNG, TIFF)    | expanded to `u8` gray/rgb/rgba  |
//! | TIFF float rgb / rgba          | `rgb_f32` / `rgba_f32`          |
//! | PFM `PF` / `Pf`                | `rgb_f32` / `gray_f32`          |
//! | EXR one channel / RGB / RGBA   | `gray_f32` / `rgb_f32` / `rgba_f32` (half widened) |
//!
//! [`Image`] has no gray + alpha layout, so gray + alpha is widened to rgba (the only lossless
//! choice). EXIF orientation and colour profiles are *not* applied: the samples are the stored
//! ones, which is what geometric pipelines (and COLMAP) expect. TIFF gray f32 cannot be read,
//! because the decoder we build on does not support it; use PFM or EXR for gray float images.
//!
//! Untrusted files are decoded defensively: the header's dimensions are checked against
//! [`DecodeLimits`] *before* any pixel buffer is allocated, and a decoder that fails — or even
//! panics — on a truncated or garbage file yields [`ImageIoError::Corrupt`], never a crash.
//!
//! # Writing
//! [`write_image`] picks an [`ImageFormat`] from the extension, encodes with [`encode_image`] and
//! writes through [`write_atomic`], so a reader never sees a half-written file.
//!
//! | format | layouts                      | depths           |
//! |--------|------------------------------|------------------|
//! | PNG    | gray, rgb, rgba              | u8, u16          |
//! | JPEG   | gray, rgb                    | u8 (lossy)       |
//! | PNM    | gray (P5), rgb (P6), rgba (P7 PAM) | u8, u16    |
//! | TIFF   | gray, rgb, rgba; rgb, rgba   | u8, u16; f32     |
//! | PFM    | gray (`Pf`), rgb (`PF`)      | f32              |
//! | EXR    | gray (`Y`), rgb, rgba        | f32 (ZIP, lossless) |
//!
//! The PNM subtype follows the image's channels, not the extension (`.pgm`, `.ppm`, `.pnm` and
//! `.pam` all select [`ImageFormat::Pnm`]). No format here stores a zero-area image: encoding one
//! is [`ImageIoError::Unsupported`].

use std::fmt;
use std::fs::{self, File};
use std::io::{self, BufWriter, Cursor, Write};
use std::panic::{self, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use image::{ColorType, ExtendedColorType, ImageDecoder, ImageEncoder, ImageError};

use crate::value::{Channels, Depth, Image, PixelData};

/// File extensions [`read_image`] and [`write_image`] understand (lower case; matching ignores
/// case).
pub const SUPPORTED_EXTENSIONS: [&str; 11] = [
    "png", "jpg", "jpeg", "pgm", "ppm", "pnm", "pam", "tif", "tiff", "pfm", "exr",
];

/// JPEG quality used when the format comes from a file extension.
pub const DEFAULT_JPEG_QUALITY: u8 = 95;

/// Bytes per PFM sample.
const PFM_SAMPLE_BYTES: usize = 4;

/// Longest header token (width, height, scale) accepted in a PFM file.
const PFM_MAX_TOKEN: usize = 64;

/// Resource limits for decoding untrusted files (defence against decompression bombs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DecodeLimits {
    /// Largest `width × height` accepted, checked against the header before decoding.
    pub max_pixels: u64,
    /// Largest decoded pixel buffer, in bytes; also passed to the decoders as their allocation
    /// budget.
    pub max_alloc_bytes: u64,
}

impl DecodeLimits {
    /// Default pixel limit: [`crate::limits::Limits::DEFAULT_MAX_IMAGE_PIXELS`].
    pub const DEFAULT_MAX_PIXELS: u64 = crate::limits::Limits::DEFAULT_MAX_IMAGE_PIXELS;
    /// Default allocation limit: [`crate::limits::Limits::DEFAULT_MAX_ALLOC_BYTES`].
    pub const DEFAULT_MAX_ALLOC_BYTES: u64 = crate::limits::Limits::DEFAULT_MAX_ALLOC_BYTES;
}

impl Default for DecodeLimits {
    /// The run's limits ([`crate::limits::get`]; by default [`Self::DEFAULT_MAX_PIXELS`] and
    /// [`Self::DEFAULT_MAX_ALLOC_BYTES`]).
    fn default() -> Self {
        let run = crate::limits::get();
        DecodeLimits {
            max_pixels: run.max_image_pixels,
            max_alloc_bytes: run.max_alloc_bytes,
        }
    }
}

/// Which decode limit an image exceeded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Limit {
    /// [`DecodeLimits::max_pixels`].
    Pixels(u64),
    /// [`DecodeLimits::max_alloc_bytes`].
    Bytes(u64),
}

impl fmt::Display for Limit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            // Name the flag to raise when the run's limit is the one that applied (a node's
            // own `max_pixels` can be lower).
            Limit::Pixels(n) if *n == crate::limits::get().max_image_pixels => {
                write!(f, "{n} pixels (--max-image-pixels)")
            }
            Limit::Pixels(n) => write!(f, "{n} pixels"),
            Limit::Bytes(n) if *n == crate::limits::get().max_alloc_bytes => {
                write!(f, "{n} bytes (--max-alloc-bytes)")
            }
            Limit::Bytes(n) => write!(f, "{n} bytes"),
        }
    }
}

/// Errors reading, decoding, encoding or writing image files. Every variant names the file; for
/// [`encode_image`], which has no file, the path is empty and left out of the message.
#[derive(Debug, thiserror::Error)]
pub enum ImageIoError {
    /// The file could not be read or written.
    #[error("{}I/O error: {error}", at(path))]
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        error: io::Error,
    },
    /// Neither the content nor the extension names a supported format.
    #[error(
        "{}unknown image format (not recognised by content or extension); supported extensions: {}",
        at(path),
        SUPPORTED_EXTENSIONS.join(", ")
    )]
    UnknownFormat {
        /// The file.
        path: PathBuf,
    },
    /// The decoder rejected the data (truncated, garbage, inconsistent header...).
    #[error("{}corrupt or unreadable image: {message}", at(path))]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// The decoder's message.
        message: String,
    },
    /// The header declares an image over the [`DecodeLimits`].
    #[error(
        "{}image is {width}×{height}, over the decode limit of {limit}",
        at(path)
    )]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// Declared width, pixels.
        width: u64,
        /// Declared height, pixels.
        height: u64,
        /// The limit exceeded.
        limit: Limit,
    },
    /// The format cannot hold this image, or the file uses a feature we do not read.
    #[error("{}{message}", at(path))]
    Unsupported {
        /// The file.
        path: PathBuf,
        /// What is unsupported, and what to use instead.
        message: String,
    },
}

impl ImageIoError {
    /// The file the error is about (empty for [`encode_image`] errors).
    pub fn path(&self) -> &Path {
        match self {
            ImageIoError::Io { path, .. }
            | ImageIoError::UnknownFormat { path }
            | ImageIoError::Corrupt { path, .. }
            | ImageIoError::TooLarge { path, .. }
            | ImageIoError::Unsupported { path, .. } => path,
        }
    }

    fn with_path(mut self, new_path: &Path) -> Self {
        match &mut self {
            ImageIoError::Io { path, .. }
            | ImageIoError::UnknownFormat { path }
            | ImageIoError::Corrupt { path, .. }
            | ImageIoError::TooLarge { path, .. }
            | ImageIoError::Unsupported { path, .. } => *path = new_path.to_path_buf(),
        }
        self
    }
}

/// `"`path`: "`, or nothing for an empty path.
fn at(path: &Path) -> String {
    if path.as_os_str().is_empty() {
        String::new()
    } else {
        format!("`{}`: ", path.display())
    }
}

fn unsupported(message: impl Into<String>) -> ImageIoError {
    ImageIoError::Unsupported {
        path: PathBuf::new(),
        message: message.into(),
    }
}

fn corrupt(path: &Path, message: impl Into<String>) -> ImageIoError {
    ImageIoError::Corrupt {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// An output file format with its encoder settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ImageFormat {
    /// PNG, lossless, u8/u16 gray/rgb/rgba.
    Png,
    /// Baseline JPEG, lossy, u8 gray/rgb.
    Jpeg {
        /// Quality 1..=100 (values outside are clamped).
        quality: u8,
    },
    /// Binary Netpbm: PGM (`P5`) for gray, PPM (`P6`) for rgb, PAM (`P7`) for rgba; u8/u16.
    Pnm,
    /// Uncompressed TIFF: u8/u16 gray/rgb/rgba and f32 rgb/rgba.
    Tiff,
    /// Portable Float Map, little-endian: f32 gray/rgb.
    Pfm,
    /// OpenEXR, ZIP-compressed: f32 gray/rgb/rgba (one channel `Y`, or `R`, `G`, `B` (`A`)).
    Exr,
}

impl ImageFormat {
    /// The format for a file extension (without the dot, any case): `png`, `jpg`/`jpeg` (quality
    /// [`DEFAULT_JPEG_QUALITY`]), `pgm`/`ppm`/`pnm`/`pam`, `tif`/`tiff`, `pfm`, `exr`.
    pub fn from_extension(ext: &str) -> Option<ImageFormat> {
        match ext.to_ascii_lowercase().as_str() {
            "png" => Some(ImageFormat::Png),
            "jpg" | "jpeg" => Some(ImageFormat::Jpeg {
                quality: DEFAULT_JPEG_QUALITY,
            }),
            "pgm" | "ppm" | "pnm" | "pam" => Some(ImageFormat::Pnm),
            "tif" | "tiff" => Some(ImageFormat::Tiff),
            "pfm" => Some(ImageFormat::Pfm),
            "exr" => Some(ImageFormat::Exr),
            _ => None,
        }
    }

    /// The format for a path's extension.
    pub fn from_path(path: &Path) -> Option<ImageFormat> {
        path.extension()
            .and_then(|e| e.to_str())
            .and_then(ImageFormat::from_extension)
    }

    /// Short upper-case name for messages.
    pub fn name(self) -> &'static str {
        match self {
            ImageFormat::Png => "PNG",
            ImageFormat::Jpeg { .. } => "JPEG",
            ImageFormat::Pnm => "PNM",
            ImageFormat::Tiff => "TIFF",
            ImageFormat::Pfm => "PFM",
            ImageFormat::Exr => "EXR",
        }
    }
}

/// A format recognised in a file, for decoding.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Detected {
    /// Decoded by the `image` crate.
    Codec(image::ImageFormat),
    /// Decoded here.
    Pfm,
    /// Decoded by the `exr_io` module.
    Exr,
}

/// Recognises a format from its first bytes.
fn sniff(bytes: &[u8]) -> Option<Detected> {
    const PNG_MAGIC: &[u8] = b"\x89PNG\r\n\x1a\n";
    let followed_by_space = |i: usize| bytes.get(i).is_some_and(u8::is_ascii_whitespace);
    if bytes.starts_with(PNG_MAGIC) {
        Some(Detected::Codec(image::ImageFormat::Png))
    } else if bytes.starts_with(&[0xFF, 0xD8, 0xFF]) {
        Some(Detected::Codec(image::ImageFormat::Jpeg))
    } else if bytes.starts_with(b"II*\0")
        || bytes.starts_with(b"MM\0*")
        || bytes.starts_with(b"II+\0")
        || bytes.starts_with(b"MM\0+")
    {
        Some(Detected::Codec(image::ImageFormat::Tiff))
    } else if bytes.starts_with(&crate::exr_io::EXR_MAGIC) {
        Some(Detected::Exr)
    } else if (bytes.starts_with(b"PF") || bytes.starts_with(b"Pf")) && followed_by_space(2) {
        Some(Detected::Pfm)
    } else if bytes.first() == Some(&b'P')
        && bytes.get(1).is_some_and(|d| (b'1'..=b'7').contains(d))
        && followed_by_space(2)
    {
        Some(Detected::Codec(image::ImageFormat::Pnm))
    } else {
        None
    }
}

/// The format an extension names, for decoding.
fn detect_by_extension(path: &Path) -> Option<Detected> {
    Some(match ImageFormat::from_path(path)? {
        ImageFormat::Png => Detected::Codec(image::ImageFormat::Png),
        ImageFormat::Jpeg { .. } => Detected::Codec(image::ImageFormat::Jpeg),
        ImageFormat::Pnm => Detected::Codec(image::ImageFormat::Pnm),
        ImageFormat::Tiff => Detected::Codec(image::ImageFormat::Tiff),
        ImageFormat::Pfm => Detected::Pfm,
        ImageFormat::Exr => Detected::Exr,
    })
}

/// Reads and decodes an image file. The format comes from the content, with the extension as a
/// fallback; see the [module docs](self) for how stored layouts map to [`Image`].
pub fn read_image(path: &Path, limits: &DecodeLimits) -> Result<Image, ImageIoError> {
    let bytes = crate::limits::read_file(path).map_err(|error| ImageIoError::Io {
        path: path.to_path_buf(),
        error,
    })?;
    decode_image(&bytes, path, limits)
}

/// Decodes an image held in memory. `path_for_errors` names it in errors and supplies the
/// extension used when the content is not recognised.
pub fn decode_image(
    bytes: &[u8],
    path_for_errors: &Path,
    limits: &DecodeLimits,
) -> Result<Image, ImageIoError> {
    let path = path_for_errors;
    let detected = sniff(bytes)
        .or_else(|| detect_by_extension(path))
        .ok_or_else(|| ImageIoError::UnknownFormat {
            path: path.to_path_buf(),
        })?;
    match detected {
        Detected::Pfm => decode_pfm(bytes, path, limits),
        Detected::Exr => panic::catch_unwind(AssertUnwindSafe(|| {
            crate::exr_io::decode_exr(bytes, path, limits)
        }))
        .unwrap_or_else(|_| Err(corrupt(path, "the EXR decoder panicked on this data"))),
        Detected::Codec(format) => {
            if format == image::ImageFormat::Jpeg && !jpeg_has_end_after_last_scan(bytes) {
                // The JPEG decoder fills a cut-off scan with grey and reports success (as
                // libjpeg does, with a "premature end" warning); a partial picture must not
                // pass for the photo.
                return Err(corrupt(
                    path,
                    "truncated JPEG: no end-of-image marker after the last scan",
                ));
            }
            // Third-party decoders face hostile bytes here; a panic in one of them must not take
            // the whole run down, so it becomes an ordinary decode error.
            panic::catch_unwind(AssertUnwindSafe(|| {
                decode_with_codec(bytes, format, path, limits)
            }))
            .unwrap_or_else(|_| Err(corrupt(path, "the decoder panicked on this data")))
        }
    }
}

/// Whether a JPEG stream has an end-of-image marker (`FF D9`) after its last start-of-scan
/// (`FF DA`). Inside entropy-coded data a `FF` byte is always stuffed (`FF 00`) or a restart
/// marker (`FF D0`–`FF D7`), so `FF D9` there is the real end; an embedded thumbnail's markers
/// come before the main image's last scan.
fn jpeg_has_end_after_last_scan(bytes: &[u8]) -> bool {
    let last_scan = bytes.windows(2).rposition(|w| w == [0xFF, 0xDA]);
    match last_scan {
        Some(at) => bytes[at..].windows(2).any(|w| w == [0xFF, 0xD9]),
        // No scan at all: the decoder reports that itself.
        None => true,
    }
}

/// Checks declared dimensions and the decoded buffer size against the limits.
fn check_limits(
    path: &Path,
    width: u64,
    height: u64,
    buffer_bytes: Option<u64>,
    limits: &DecodeLimits,
) -> Result<(), ImageIoError> {
    let too_large = |limit| ImageIoError::TooLarge {
        path: path.to_path_buf(),
        width,
        height,
        limit,
    };
    match width.checked_mul(height) {
        Some(pixels) if pixels <= limits.max_pixels => {}
        _ => return Err(too_large(Limit::Pixels(limits.max_pixels))),
    }
    match buffer_bytes {
        Some(bytes) if bytes <= limits.max_alloc_bytes => Ok(()),
        _ => Err(too_large(Limit::Bytes(limits.max_alloc_bytes))),
    }
}

fn decode_with_codec(
    bytes: &[u8],
    format: image::ImageFormat,
    path: &Path,
    limits: &DecodeLimits,
) -> Result<Image, ImageIoError> {
    let mut reader = image::ImageReader::with_format(Cursor::new(bytes), format);
    let mut codec_limits = image::Limits::default();
    codec_limits.max_alloc = Some(limits.max_alloc_bytes);
    reader.limits(codec_limits);
    // Building the decoder parses the header only; nothing of pixel size is allocated yet.
    let decoder = reader
        .into_decoder()
        .map_err(|e| decode_error(e, path, None, limits))?;
    let (width, height) = decoder.dimensions();
    let total = decoder.total_bytes();
    check_limits(
        path,
        u64::from(width),
        u64::from(height),
        Some(total),
        limits,
    )?;
    let color = decoder.color_type();
    let len = usize::try_from(total).map_err(|_| ImageIoError::TooLarge {
        path: path.to_path_buf(),
        width: u64::from(width),
        height: u64::from(height),
        limit: Limit::Bytes(limits.max_alloc_bytes),
    })?;
    let mut buf = vec![0u8; len];
    decoder
        .read_image(&mut buf)
        .map_err(|e| decode_error(e, path, Some((width, height)), limits))?;
    image_from_native(width as usize, height as usize, color, buf).map_err(|e| e.with_path(path))
}

fn decode_error(
    error: ImageError,
    path: &Path,
    dims: Option<(u32, u32)>,
    limits: &DecodeLimits,
) -> ImageIoError {
    match (error, dims) {
        (ImageError::Limits(_), Some((w, h))) => ImageIoError::TooLarge {
            path: path.to_path_buf(),
            width: u64::from(w),
            height: u64::from(h),
            limit: Limit::Bytes(limits.max_alloc_bytes),
        },
        (ImageError::Unsupported(e), _) => ImageIoError::Unsupported {
            path: path.to_path_buf(),
            message: e.to_string(),
        },
        (other, _) => corrupt(path, other.to_string()),
    }
}

/// Builds an [`Image`] from a decoder's native-endian buffer.
fn image_from_native(
    width: usize,
    height: usize,
    color: ColorType,
    buf: Vec<u8>,
) -> Result<Image, ImageIoError> {
    let built = match color {
        ColorType::L8 => Image::from_u8(width, height, Channels::Gray, buf),
        ColorType::Rgb8 => Image::from_u8(width, height, Channels::Rgb, buf),
        ColorType::Rgba8 => Image::from_u8(width, height, Channels::Rgba, buf),
        ColorType::La8 => Image::from_u8(width, height, Channels::Rgba, gray_alpha_to_rgba(&buf)),
        ColorType::L16 => Image::from_u16(width, height, Channels::Gray, u16_from_ne(&buf)),
        ColorType::Rgb16 => Image::from_u16(width, height, Channels::Rgb, u16_from_ne(&buf)),
        ColorType::Rgba16 => Image::from_u16(width, height, Channels::Rgba, u16_from_ne(&buf)),
        ColorType::La16 => Image::from_u16(
            width,
            height,
            Channels::Rgba,
            gray_alpha_to_rgba(&u16_from_ne(&buf)),
        ),
        ColorType::Rgb32F => Image::from_f32(width, height, Channels::Rgb, f32_from_ne(&buf)),
        ColorType::Rgba32F => Image::from_f32(width, height, Channels::Rgba, f32_from_ne(&buf)),
        other => {
            return Err(unsupported(format!(
                "pixel type {other:?} is not supported"
            )));
        }
    };
    built.map_err(|e| ImageIoError::Corrupt {
        path: PathBuf::new(),
        message: e.to_string(),
    })
}

fn gray_alpha_to_rgba<T: Copy>(samples: &[T]) -> Vec<T> {
    let mut out = Vec::with_capacity(samples.len() * 2);
    for [l, a] in samples.as_chunks::<2>().0 {
        out.extend_from_slice(&[*l, *l, *l, *a]);
    }
    out
}

fn u16_from_ne(bytes: &[u8]) -> Vec<u16> {
    bytes
        .as_chunks::<2>()
        .0
        .iter()
        .map(|b| u16::from_ne_bytes(*b))
        .collect()
}

fn f32_from_ne(bytes: &[u8]) -> Vec<f32> {
    bytes
        .as_chunks::<4>()
        .0
        .iter()
        .map(|b| f32::from_ne_bytes(*b))
        .collect()
}

/// Parses a PFM file (Portable Float Map).
///
/// Layout: `PF` (rgb) or `Pf` (gray), whitespace, width, whitespace, height, whitespace, a scale,
/// exactly one whitespace byte, then `width × height × channels` 4-byte floats, rows stored
/// bottom-to-top. A negative scale means little-endian samples, a positive one big-endian; its
/// magnitude is informational and does not change the samples. Bytes after the samples are
/// ignored.
fn decode_pfm(bytes: &[u8], path: &Path, limits: &DecodeLimits) -> Result<Image, ImageIoError> {
    let channels = match bytes.get(..2) {
        Some(b"PF") => Channels::Rgb,
        Some(b"Pf") => Channels::Gray,
        _ => return Err(corrupt(path, "PFM: missing `PF`/`Pf` magic")),
    };
    let mut pos = 2;
    let width = pfm_token(bytes, &mut pos, path, "width")?;
    let width = parse_dimension(width).ok_or_else(|| corrupt(path, "PFM: invalid width"))?;
    let height = pfm_token(bytes, &mut pos, path, "height")?;
    let height = parse_dimension(height).ok_or_else(|| corrupt(path, "PFM: invalid height"))?;
    let scale = pfm_token(bytes, &mut pos, path, "scale")?;
    let scale: f64 = std::str::from_utf8(scale)
        .ok()
        .and_then(|s| s.parse().ok())
        .filter(|s: &f64| s.is_finite() && *s != 0.0)
        .ok_or_else(|| corrupt(path, "PFM: the scale must be a finite, non-zero number"))?;
    if !bytes.get(pos).is_some_and(u8::is_ascii_whitespace) {
        return Err(corrupt(
            path,
            "PFM: expected one whitespace byte after the scale",
        ));
    }
    pos += 1;
    let sample_bytes = width
        .checked_mul(height)
        .and_then(|n| n.checked_mul(channels.count() as u64))
        .and_then(|n| n.checked_mul(PFM_SAMPLE_BYTES as u64));
    check_limits(path, width, height, sample_bytes, limits)?;
    let too_large = || ImageIoError::TooLarge {
        path: path.to_path_buf(),
        width,
        height,
        limit: Limit::Bytes(limits.max_alloc_bytes),
    };
    let (w, h) = (
        usize::try_from(width).map_err(|_| too_large())?,
        usize::try_from(height).map_err(|_| too_large())?,
    );
    let needed = sample_bytes
        .and_then(|n| usize::try_from(n).ok())
        .ok_or_else(too_large)?;
    let body = bytes.get(pos..).unwrap_or_default();
    if body.len() < needed {
        return Err(corrupt(
            path,
            format!(
                "PFM: truncated, {} of {needed} sample bytes present",
                body.len()
            ),
        ));
    }
    let little_endian = scale < 0.0;
    let row_bytes = w * channels.count() * PFM_SAMPLE_BYTES;
    let mut samples = Vec::with_capacity(needed / PFM_SAMPLE_BYTES);
    if row_bytes > 0 {
        // Stored bottom row first: walk the stored rows in reverse to get top-to-bottom.
        for row in body[..needed].chunks_exact(row_bytes).rev() {
            samples.extend(row.as_chunks::<4>().0.iter().map(|b| {
                if little_endian {
                    f32::from_le_bytes(*b)
                } else {
                    f32::from_be_bytes(*b)
                }
            }));
        }
    }
    Image::from_f32(w, h, channels, samples).map_err(|e| corrupt(path, e.to_string()))
}

/// Skips whitespace and returns the next whitespace-delimited header token.
fn pfm_token<'a>(
    bytes: &'a [u8],
    pos: &mut usize,
    path: &Path,
    what: &str,
) -> Result<&'a [u8], ImageIoError> {
    let rest = bytes.get(*pos..).unwrap_or_default();
    let start = rest
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .ok_or_else(|| corrupt(path, format!("PFM: header ends before the {what}")))?;
    let len = rest[start..]
        .iter()
        .take(PFM_MAX_TOKEN + 1)
        .position(u8::is_ascii_whitespace)
        .ok_or_else(|| corrupt(path, format!("PFM: header ends inside the {what}")))?;
    *pos += start + len;
    Ok(&rest[start..start + len])
}

fn parse_dimension(token: &[u8]) -> Option<u64> {
    if token.is_empty() || !token.iter().all(u8::is_ascii_digit) {
        return None;
    }
    std::str::from_utf8(token).ok()?.parse().ok()
}

/// Encodes an image in `format`. Errors are [`ImageIoError::Unsupported`] when the format cannot
/// hold the image's layout, depth or size (see the table in the [module docs](self)); their path
/// is empty.
pub fn encode_image(image: &Image, format: ImageFormat) -> Result<Vec<u8>, ImageIoError> {
    let (channels, depth) = (image.channels(), image.depth());
    if image.is_empty() {
        return Err(unsupported(format!(
            "{} cannot store a zero-area image ({}×{})",
            format.name(),
            image.width(),
            image.height()
        )));
    }
    match format {
        ImageFormat::Png => {
            if depth == Depth::F32 {
                return Err(unsupported(
                    "PNG cannot store f32 samples; use .pfm or .tiff",
                ));
            }
            let (w, h) = dims_u32(image, format)?;
            let mut out = Vec::new();
            image::codecs::png::PngEncoder::new(&mut out)
                .write_image(&native_bytes(image), w, h, codec_color(channels, depth)?)
                .map_err(encode_error)?;
            Ok(out)
        }
        ImageFormat::Jpeg { quality } => {
            if depth != Depth::U8 || channels == Channels::Rgba {
                return Err(unsupported(format!(
                    "JPEG stores only 8-bit gray or rgb, not {}; use .png or .tiff",
                    image.format()
                )));
            }
            let (w, h) = dims_u32(image, format)?;
            let mut out = Vec::new();
            image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality.clamp(1, 100))
                .write_image(&native_bytes(image), w, h, codec_color(channels, depth)?)
                .map_err(encode_error)?;
            Ok(out)
        }
        ImageFormat::Pnm => encode_pnm(image),
        ImageFormat::Tiff => {
            if depth == Depth::F32 && channels == Channels::Gray {
                return Err(unsupported(
                    "the TIFF writer cannot store gray f32 samples; use .pfm",
                ));
            }
            let (w, h) = dims_u32(image, format)?;
            let mut out = Cursor::new(Vec::new());
            image::codecs::tiff::TiffEncoder::new(&mut out)
                .write_image(&native_bytes(image), w, h, codec_color(channels, depth)?)
                .map_err(encode_error)?;
            Ok(out.into_inner())
        }
        ImageFormat::Pfm => encode_pfm(image),
        ImageFormat::Exr => crate::exr_io::encode_exr(image),
    }
}

fn dims_u32(image: &Image, format: ImageFormat) -> Result<(u32, u32), ImageIoError> {
    match (u32::try_from(image.width()), u32::try_from(image.height())) {
        (Ok(w), Ok(h)) => Ok((w, h)),
        _ => Err(unsupported(format!(
            "{} cannot store a {}×{} image",
            format.name(),
            image.width(),
            image.height()
        ))),
    }
}

fn encode_error(error: ImageError) -> ImageIoError {
    match error {
        ImageError::IoError(error) => ImageIoError::Io {
            path: PathBuf::new(),
            error,
        },
        other => unsupported(other.to_string()),
    }
}

/// The `image` crate's name for a layout; gray f32 has none.
fn codec_color(channels: Channels, depth: Depth) -> Result<ExtendedColorType, ImageIoError> {
    Ok(match (channels, depth) {
        (Channels::Gray, Depth::U8) => ExtendedColorType::L8,
        (Channels::Rgb, Depth::U8) => ExtendedColorType::Rgb8,
        (Channels::Rgba, Depth::U8) => ExtendedColorType::Rgba8,
        (Channels::Gray, Depth::U16) => ExtendedColorType::L16,
        (Channels::Rgb, Depth::U16) => ExtendedColorType::Rgb16,
        (Channels::Rgba, Depth::U16) => ExtendedColorType::Rgba16,
        (Channels::Rgb, Depth::F32) => ExtendedColorType::Rgb32F,
        (Channels::Rgba, Depth::F32) => ExtendedColorType::Rgba32F,
        (Channels::Gray, Depth::F32) => {
            return Err(unsupported("gray f32 cannot be encoded here; use .pfm"));
        }
    })
}

/// The samples as native-endian bytes, the layout the `image` encoders take.
fn native_bytes(image: &Image) -> Vec<u8> {
    match image.data() {
        PixelData::U8(v) => v.clone(),
        PixelData::U16(v) => {
            let mut out = vec![0u8; v.len() * 2];
            for (dst, s) in out.as_chunks_mut::<2>().0.iter_mut().zip(v) {
                *dst = s.to_ne_bytes();
            }
            out
        }
        PixelData::F32(v) => {
            let mut out = vec![0u8; v.len() * 4];
            for (dst, s) in out.as_chunks_mut::<4>().0.iter_mut().zip(v) {
                *dst = s.to_ne_bytes();
            }
            out
        }
    }
}

/// Binary Netpbm: `P5` gray, `P6` rgb, `P7` (PAM) rgba; 16-bit samples big-endian (Netpbm's rule).
fn encode_pnm(image: &Image) -> Result<Vec<u8>, ImageIoError> {
    let (w, h) = (image.width(), image.height());
    let maxval = match image.depth() {
        Depth::U8 => 255,
        Depth::U16 => 65535,
        Depth::F32 => {
            return Err(unsupported(
                "PNM stores only 8- or 16-bit samples, not f32; use .pfm or .tiff",
            ));
        }
    };
    let header = match image.channels() {
        Channels::Gray => format!("P5\n{w} {h}\n{maxval}\n"),
        Channels::Rgb => format!("P6\n{w} {h}\n{maxval}\n"),
        Channels::Rgba => format!(
            "P7\nWIDTH {w}\nHEIGHT {h}\nDEPTH 4\nMAXVAL {maxval}\nTUPLTYPE RGB_ALPHA\nENDHDR\n"
        ),
    };
    let mut out = Vec::with_capacity(header.len() + image.byte_size());
    out.extend_from_slice(header.as_bytes());
    match image.data() {
        PixelData::U8(v) => out.extend_from_slice(v),
        PixelData::U16(v) => {
            let start = out.len();
            out.resize(start + v.len() * 2, 0);
            for (dst, s) in out[start..].as_chunks_mut::<2>().0.iter_mut().zip(v) {
                *dst = s.to_be_bytes();
            }
        }
        PixelData::F32(_) => {}
    }
    Ok(out)
}

/// PFM, little-endian (scale `-1.0`), rows bottom-to-top.
fn encode_pfm(image: &Image) -> Result<Vec<u8>, ImageIoError> {
    let magic = match image.channels() {
        Channels::Gray => "Pf",
        Channels::Rgb => "PF",
        Channels::Rgba => {
            return Err(unsupported(
                "PFM stores only gray or rgb; use .tiff for rgba f32",
            ));
        }
    };
    let Some(samples) = image.as_f32() else {
        return Err(unsupported(format!(
            "PFM stores only f32 samples, not {}; use .png, .pnm or .tiff",
            image.depth().name()
        )));
    };
    let header = format!("{magic}\n{} {}\n-1.0\n", image.width(), image.height());
    let mut out = vec![0u8; header.len() + samples.len() * PFM_SAMPLE_BYTES];
    let (head, body) = out.split_at_mut(header.len());
    head.copy_from_slice(header.as_bytes());
    let row = image.row_stride();
    if row > 0 {
        for (dst_row, src_row) in body
            .chunks_exact_mut(row * PFM_SAMPLE_BYTES)
            .zip(samples.chunks_exact(row).rev())
        {
            for (dst, s) in dst_row.as_chunks_mut::<4>().0.iter_mut().zip(src_row) {
                *dst = s.to_le_bytes();
            }
        }
    }
    Ok(out)
}

/// Encodes `image` in the format its extension names and writes it atomically.
pub fn write_image(path: &Path, image: &Image) -> Result<(), ImageIoError> {
    let format = ImageFormat::from_path(path).ok_or_else(|| ImageIoError::UnknownFormat {
        path: path.to_path_buf(),
    })?;
    let bytes = encode_image(image, format).map_err(|e| e.with_path(path))?;
    write_atomic(path, &bytes).map_err(|error| ImageIoError::Io {
        path: path.to_path_buf(),
        error,
    })
}

/// Distinguishes temp files of one process.
static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// Longest part of the target's name kept in a temp file's name.
const TEMP_NAME_MAX_CHARS: usize = 100;

/// Writes `bytes` to `path` atomically; see [`write_atomic_with`].
pub fn write_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    write_atomic_with(path, |w| w.write_all(bytes))
}

/// Writes a file atomically: `write` streams the content (buffered) into a temp file in the
/// target's directory, named `.{name}.{pid}.{counter}.ocellus.tmp`; the file is flushed and synced, then
/// renamed over `path`. Readers see the old file or the complete new one, never a partial one. On
/// any failure the temp file is removed and `path` is left as it was. The directory must exist.
pub fn write_atomic_with(
    path: &Path,
    write: impl FnOnce(&mut dyn Write) -> io::Result<()>,
) -> io::Result<()> {
    let name = path.file_name().ok_or_else(|| {
        io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("`{}` has no file name", path.display()),
        )
    })?;
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let short: String = name
        .to_string_lossy()
        .chars()
        .take(TEMP_NAME_MAX_CHARS)
        .collect();
    let tmp = dir.join(format!(
        ".{short}.{}.{}.ocellus.tmp",
        std::process::id(),
        TEMP_COUNTER.fetch_add(1, Ordering::Relaxed)
    ));
    let file = crate::temp_files::create(&tmp)?;
    let result = fill_and_commit(file, &tmp, path, write);
    if result.is_err() {
        // Best effort: the original error is the one worth reporting.
        let _ = fs::remove_file(&tmp);
    }
    crate::temp_files::forget(&tmp);
    if result.is_ok() {
        sync_dir(dir);
    }
    result
}

fn fill_and_commit(
    file: File,
    tmp: &Path,
    path: &Path,
    write: impl FnOnce(&mut dyn Write) -> io::Result<()>,
) -> io::Result<()> {
    let mut writer = BufWriter::with_capacity(1 << 16, file);
    write(&mut writer)?;
    let file = writer
        .into_inner()
        .map_err(io::IntoInnerError::into_error)?;
    file.sync_all()?;
    drop(file);
    fs::rename(tmp, path)
}

/// Makes the rename durable where the platform allows syncing a directory.
fn sync_dir(dir: &Path) {
    #[cfg(unix)]
    {
        // Durability only: the rename already happened, so a failure here changes nothing a
        // reader can see.
        let _ = File::open(dir).and_then(|d| d.sync_all());
    }
    #[cfg(not(unix))]
    let _ = dir;
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fresh, empty scratch directory for one test.
    fn scratch(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("ocellus-image-io-{}-{name}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn files_in(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    /// A deterministic test image with distinct, smoothly varying samples.
    fn test_image(w: usize, h: usize, channels: Channels, depth: Depth) -> Image {
        let c = channels.count();
        let n = w * h * c;
        let value = |i: usize| {
            let (p, ch) = (i / c, i % c);
            let (x, y) = (p % w, p / w);
            (x * 7 + y * 5 + ch * 40) as f64 / ((w * 7 + h * 5 + c * 40) as f64)
        };
        match depth {
            Depth::U8 => Image::from_u8(
                w,
                h,
                channels,
                (0..n).map(|i| (value(i) * 255.0) as u8).collect(),
            ),
            Depth::U16 => Image::from_u16(
                w,
                h,
                channels,
                (0..n)
                    .map(|i| (value(i) * 65535.0) as u16 ^ 0x0101)
                    .collect(),
            ),
            Depth::F32 => Image::from_f32(
                w,
                h,
                channels,
                (0..n).map(|i| (value(i) * 3.0 - 1.0) as f32).collect(),
            ),
        }
        .unwrap()
    }

    const ALL_CHANNELS: [Channels; 3] = [Channels::Gray, Channels::Rgb, Channels::Rgba];
    const ALL_DEPTHS: [Depth; 3] = [Depth::U8, Depth::U16, Depth::F32];

    fn supported(format: ImageFormat, channels: Channels, depth: Depth) -> bool {
        match format {
            ImageFormat::Png | ImageFormat::Pnm => depth != Depth::F32,
            ImageFormat::Jpeg { .. } => depth == Depth::U8 && channels != Channels::Rgba,
            ImageFormat::Tiff => !(depth == Depth::F32 && channels == Channels::Gray),
            ImageFormat::Pfm => depth == Depth::F32 && channels != Channels::Rgba,
            ImageFormat::Exr => depth == Depth::F32,
        }
    }

    const FORMATS: [ImageFormat; 6] = [
        ImageFormat::Png,
        ImageFormat::Jpeg { quality: 95 },
        ImageFormat::Pnm,
        ImageFormat::Tiff,
        ImageFormat::Pfm,
        ImageFormat::Exr,
    ];

    #[test]
    fn round_trips_every_supported_combination() {
        let limits = DecodeLimits::default();
        let mut checked = 0;
        for format in FORMATS {
            for channels in ALL_CHANNELS {
                for depth in ALL_DEPTHS {
                    let image = test_image(13, 7, channels, depth);
                    let encoded = encode_image(&image, format);
                    if !supported(format, channels, depth) {
                        assert!(
                            matches!(encoded, Err(ImageIoError::Unsupported { .. })),
                            "{format:?} {channels:?} {depth:?} should be unsupported"
                        );
                        continue;
                    }
                    let bytes = encoded.unwrap();
                    let decoded = decode_image(&bytes, Path::new("x"), &limits).unwrap();
                    assert_eq!(decoded.format(), image.format(), "{format:?}");
                    assert_eq!((decoded.width(), decoded.height()), (13, 7));
                    if let ImageFormat::Jpeg { .. } = format {
                        let (a, b) = (image.as_u8().unwrap(), decoded.as_u8().unwrap());
                        let max = a.iter().zip(b).map(|(x, y)| x.abs_diff(*y)).max().unwrap();
                        assert!(max <= 12, "{channels:?}: JPEG error {max}");
                    } else {
                        assert_eq!(decoded, image, "{format:?} {channels:?} {depth:?}");
                    }
                    checked += 1;
                }
            }
        }
        // PNG 6 + JPEG 2 + PNM 6 + TIFF 8 + PFM 2 + EXR 3.
        assert_eq!(checked, 27);
    }

    #[test]
    fn f32_bits_survive_pfm_and_tiff() {
        let special = [
            f32::NAN,
            -0.0,
            f32::INFINITY,
            f32::MIN_POSITIVE / 4.0,
            1e30,
            -7.5,
        ];
        let image = Image::from_f32(2, 1, Channels::Rgb, special.to_vec()).unwrap();
        for format in [ImageFormat::Pfm, ImageFormat::Tiff, ImageFormat::Exr] {
            let bytes = encode_image(&image, format).unwrap();
            let back = decode_image(&bytes, Path::new(""), &DecodeLimits::default()).unwrap();
            let bits = |i: &Image| {
                i.as_f32()
                    .unwrap()
                    .iter()
                    .map(|v| v.to_bits())
                    .collect::<Vec<_>>()
            };
            assert_eq!(bits(&back), bits(&image), "{format:?}");
        }
    }

    #[test]
    fn exr_reads_half_floats_and_rejects_bad_files() {
        use exr::prelude::{
            AnyChannel, AnyChannels, Encoding, FlatSamples, Image as ExrImage, Layer,
            LayerAttributes, SmallVec, WritableImage, f16,
        };
        // A half-float "Z" channel (a depth map as renderers write it) reads as gray f32.
        let depth: Vec<f16> = [0.5f32, 1.25, -2.0, 65504.0, 0.0, 3.0]
            .iter()
            .map(|&v| f16::from_f32(v))
            .collect();
        let channels: SmallVec<[AnyChannel<FlatSamples>; 4]> =
            SmallVec::from_vec(vec![AnyChannel::new("Z", FlatSamples::F16(depth))]);
        let layer = Layer::new(
            (3, 2),
            LayerAttributes::default(),
            Encoding::UNCOMPRESSED,
            AnyChannels::sort(channels),
        );
        let mut bytes = Cursor::new(Vec::new());
        ExrImage::from_layer(layer)
            .write()
            .to_buffered(&mut bytes)
            .unwrap();
        let bytes = bytes.into_inner();
        let image = decode_image(&bytes, Path::new("depth.exr"), &DecodeLimits::default()).unwrap();
        assert_eq!(image.channels(), Channels::Gray);
        assert_eq!(
            image.as_f32().unwrap(),
            &[0.5, 1.25, -2.0, 65504.0, 0.0, 3.0]
        );
        // Over the pixel limit: refused before decoding.
        let small = DecodeLimits {
            max_pixels: 5,
            ..DecodeLimits::default()
        };
        let err = decode_image(&bytes, Path::new("depth.exr"), &small).unwrap_err();
        assert!(matches!(err, ImageIoError::TooLarge { .. }), "{err}");
        // Truncated: a clean corruption error naming the file.
        for cut in [4, 20, bytes.len() / 2, bytes.len() - 3] {
            let err = decode_image(
                &bytes[..cut],
                Path::new("cut.exr"),
                &DecodeLimits::default(),
            )
            .unwrap_err();
            assert!(err.to_string().contains("cut.exr"), "{err}");
        }
    }

    #[test]
    fn gray_alpha_becomes_rgba() {
        let mut png = Vec::new();
        image::codecs::png::PngEncoder::new(&mut png)
            .write_image(&[10, 200, 30, 40], 2, 1, ExtendedColorType::La8)
            .unwrap();
        let image = decode_image(&png, Path::new("a.png"), &DecodeLimits::default()).unwrap();
        assert_eq!(image.channels(), Channels::Rgba);
        assert_eq!(image.as_u8().unwrap(), &[10, 10, 10, 200, 30, 30, 30, 40]);
    }

    /// Hand-built 2×2 PFM: top row (1, 2), bottom row (3, 4); stored bottom row first.
    fn pfm_2x2(little_endian: bool) -> Vec<u8> {
        let mut bytes = if little_endian {
            b"Pf\n2 2\n-1.0\n".to_vec()
        } else {
            b"Pf\n2 2\n1.0\n".to_vec()
        };
        for v in [3.0f32, 4.0, 1.0, 2.0] {
            let b = if little_endian {
                v.to_le_bytes()
            } else {
                v.to_be_bytes()
            };
            bytes.extend_from_slice(&b);
        }
        bytes
    }

    #[test]
    fn pfm_layout_is_bottom_to_top_in_both_endiannesses() {
        let limits = DecodeLimits::default();
        for le in [true, false] {
            let image = decode_image(&pfm_2x2(le), Path::new("t.pfm"), &limits).unwrap();
            assert_eq!(image.channels(), Channels::Gray);
            assert_eq!(image.as_f32().unwrap(), &[1.0, 2.0, 3.0, 4.0], "le={le}");
        }
        let image = Image::from_f32(2, 2, Channels::Gray, vec![1.0, 2.0, 3.0, 4.0]).unwrap();
        assert_eq!(
            encode_image(&image, ImageFormat::Pfm).unwrap(),
            pfm_2x2(true)
        );

        // rgb: the magic is `PF` and samples are interleaved.
        let rgb = Image::from_f32(1, 2, Channels::Rgb, vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]).unwrap();
        let bytes = encode_image(&rgb, ImageFormat::Pfm).unwrap();
        let mut expected = b"PF\n1 2\n-1.0\n".to_vec();
        for v in [4.0f32, 5.0, 6.0, 1.0, 2.0, 3.0] {
            expected.extend_from_slice(&v.to_le_bytes());
        }
        assert_eq!(bytes, expected);
    }

    #[test]
    fn pfm_header_variants() {
        let limits = DecodeLimits::default();
        // Extra whitespace between tokens and trailing bytes after the samples are accepted.
        let mut bytes = b"Pf  1\t1\r\n-0.5\n".to_vec();
        bytes.extend_from_slice(&9.5f32.to_le_bytes());
        bytes.extend_from_slice(b"junk");
        let image = decode_image(&bytes, Path::new(""), &limits).unwrap();
        assert_eq!(image.as_f32().unwrap(), &[9.5]);
        for bad in [
            &b"Pf\n1 1\n0\n\0\0\0\0"[..],
            b"Pf\n1 1\nnan\n\0\0\0\0",
            b"Pf\n-1 1\n-1\n\0\0\0\0",
            b"Pf\n1 1\n-1",
            b"Pf\n1 1\n-1\n\0\0\0",
        ] {
            let err = decode_image(bad, Path::new("b.pfm"), &limits).unwrap_err();
            assert!(matches!(err, ImageIoError::Corrupt { .. }), "{err}");
        }
    }

    /// CRC-32 (IEEE) for building PNG chunks in tests.
    fn crc32(bytes: &[u8]) -> u32 {
        let mut crc = !0u32;
        for &b in bytes {
            crc ^= u32::from(b);
            for _ in 0..8 {
                crc = if crc & 1 != 0 {
                    (crc >> 1) ^ 0xEDB8_8320
                } else {
                    crc >> 1
                };
            }
        }
        !crc
    }

    fn png_chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
        out.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let mut body = kind.to_vec();
        body.extend_from_slice(data);
        out.extend_from_slice(&body);
        out.extend_from_slice(&crc32(&body).to_be_bytes());
    }

    #[test]
    fn limits_reject_huge_headers_before_decoding() {
        let limits = DecodeLimits::default();
        // A PNG whose header claims 100000×100000 rgba8 (40 GB decoded) with a tiny body.
        let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
        let mut ihdr = Vec::new();
        ihdr.extend_from_slice(&100_000u32.to_be_bytes());
        ihdr.extend_from_slice(&100_000u32.to_be_bytes());
        ihdr.extend_from_slice(&[8, 6, 0, 0, 0]);
        png_chunk(&mut png, b"IHDR", &ihdr);
        png_chunk(
            &mut png,
            b"IDAT",
            &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01],
        );
        png_chunk(&mut png, b"IEND", &[]);
        let err = decode_image(&png, Path::new("bomb.png"), &limits).unwrap_err();
        assert!(
            matches!(
                err,
                ImageIoError::TooLarge {
                    width: 100_000,
                    height: 100_000,
                    limit: Limit::Pixels(_),
                    ..
                }
            ),
            "{err}"
        );

        let pfm = b"PF\n100000 100000\n-1\n\0\0\0\0";
        let err = decode_image(pfm, Path::new("bomb.pfm"), &limits).unwrap_err();
        assert!(matches!(err, ImageIoError::TooLarge { .. }), "{err}");

        // Small limits apply to ordinary files too.
        let small = DecodeLimits {
            max_pixels: 15,
            ..DecodeLimits::default()
        };
        let image = test_image(4, 4, Channels::Gray, Depth::U8);
        let png = encode_image(&image, ImageFormat::Png).unwrap();
        assert!(matches!(
            decode_image(&png, Path::new(""), &small),
            Err(ImageIoError::TooLarge {
                width: 4,
                height: 4,
                ..
            })
        ));
        let bytes_limit = DecodeLimits {
            max_alloc_bytes: 15,
            ..DecodeLimits::default()
        };
        assert!(matches!(
            decode_image(&png, Path::new(""), &bytes_limit),
            Err(ImageIoError::TooLarge {
                limit: Limit::Bytes(15),
                ..
            })
        ));
    }

    /// Small xorshift generator: deterministic garbage without a dependency.
    struct XorShift(u64);

    impl XorShift {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }
    }

    fn assert_fails_cleanly(bytes: &[u8], what: &str) {
        if let Err(ImageIoError::Corrupt { message, .. }) =
            decode_image(bytes, Path::new("fuzz.bin"), &DecodeLimits::default())
        {
            assert!(!message.contains("panicked"), "{what}: decoder panicked");
        }
    }

    #[test]
    fn a_truncated_jpeg_is_an_error_and_a_whole_one_is_not() {
        let pixels: Vec<u8> = (0..64 * 48 * 3).map(|i| (i * 7 % 251) as u8).collect();
        let image = Image::from_u8(64, 48, Channels::Rgb, pixels).unwrap();
        let bytes = encode_image(&image, ImageFormat::Jpeg { quality: 90 }).unwrap();
        let path = Path::new("cut.jpg");
        let limits = DecodeLimits::default();
        assert!(decode_image(&bytes, path, &limits).is_ok());
        // Trailing bytes after the end marker are tolerated, as every decoder does.
        let mut padded = bytes.clone();
        padded.extend_from_slice(&[0, 0, 0]);
        assert!(decode_image(&padded, path, &limits).is_ok());
        for keep in [bytes.len() - 2, bytes.len() * 3 / 4, bytes.len() / 2] {
            let err = decode_image(&bytes[..keep], path, &limits).unwrap_err();
            assert!(err.to_string().contains("truncated JPEG"), "{keep}: {err}");
        }
    }

    #[test]
    fn truncated_files_never_panic() {
        for (format, channels, depth) in [
            (ImageFormat::Png, Channels::Rgb, Depth::U8),
            (ImageFormat::Png, Channels::Gray, Depth::U16),
            (ImageFormat::Pfm, Channels::Rgb, Depth::F32),
            (ImageFormat::Tiff, Channels::Rgba, Depth::U16),
            (ImageFormat::Tiff, Channels::Rgb, Depth::F32),
            (ImageFormat::Jpeg { quality: 80 }, Channels::Rgb, Depth::U8),
            (ImageFormat::Pnm, Channels::Rgba, Depth::U8),
            (ImageFormat::Pnm, Channels::Gray, Depth::U16),
        ] {
            let image = test_image(5, 4, channels, depth);
            let bytes = encode_image(&image, format).unwrap();
            for cut in 0..bytes.len() {
                let truncated = &bytes[..cut];
                assert_fails_cleanly(truncated, &format!("{format:?} cut at {cut}"));
                if format == ImageFormat::Pfm {
                    assert!(
                        decode_image(truncated, Path::new(""), &DecodeLimits::default()).is_err()
                    );
                }
            }
            // Flip bytes one at a time as well: a corrupt body must fail or decode, not crash.
            for i in 0..bytes.len() {
                let mut flipped = bytes.clone();
                flipped[i] ^= 0xA5;
                assert_fails_cleanly(&flipped, &format!("{format:?} flipped at {i}"));
            }
        }
    }

    #[test]
    fn random_bytes_never_panic() {
        let mut rng = XorShift(0x9E37_79B9_7F4A_7C15);
        let prefixes: [&[u8]; 8] = [
            b"",
            b"\x89PNG\r\n\x1a\n",
            b"\xFF\xD8\xFF",
            b"II*\0",
            b"MM\0*",
            b"PF\n",
            b"P6\n",
            b"P7\n",
        ];
        for round in 0..400 {
            let prefix = prefixes[round % prefixes.len()];
            let len = (rng.next() % 300) as usize;
            let mut bytes = prefix.to_vec();
            bytes.extend((0..len).map(|_| rng.next() as u8));
            assert_fails_cleanly(&bytes, &format!("round {round}"));
        }
        let err = decode_image(b"hello", Path::new("notes.txt"), &DecodeLimits::default());
        assert!(matches!(err, Err(ImageIoError::UnknownFormat { .. })));
    }

    #[test]
    fn format_comes_from_content_before_extension() {
        let image = test_image(3, 2, Channels::Rgb, Depth::U8);
        let png = encode_image(&image, ImageFormat::Png).unwrap();
        let read = decode_image(&png, Path::new("mislabelled.jpg"), &DecodeLimits::default());
        assert_eq!(read.unwrap(), image);
        // Unknown content falls back to the extension's decoder, which then reports corruption.
        let err = decode_image(b"\0\0\0\0", Path::new("x.png"), &DecodeLimits::default());
        assert!(matches!(err, Err(ImageIoError::Corrupt { .. })));
    }

    #[test]
    fn extensions_map_to_formats() {
        assert_eq!(ImageFormat::from_extension("PNG"), Some(ImageFormat::Png));
        assert_eq!(
            ImageFormat::from_extension("jpeg"),
            Some(ImageFormat::Jpeg { quality: 95 })
        );
        for ext in ["pgm", "ppm", "pnm", "pam"] {
            assert_eq!(ImageFormat::from_extension(ext), Some(ImageFormat::Pnm));
        }
        assert_eq!(ImageFormat::from_extension("tif"), Some(ImageFormat::Tiff));
        assert_eq!(ImageFormat::from_extension("pfm"), Some(ImageFormat::Pfm));
        assert_eq!(ImageFormat::from_extension("EXR"), Some(ImageFormat::Exr));
        assert_eq!(ImageFormat::from_extension("bmp"), None);
        for ext in SUPPORTED_EXTENSIONS {
            assert!(ImageFormat::from_extension(ext).is_some());
        }
    }

    #[test]
    fn empty_images_are_unsupported_everywhere() {
        for format in FORMATS {
            let image = Image::zeros(
                0,
                3,
                crate::value::PixelFormat {
                    channels: Channels::Gray,
                    depth: if matches!(format, ImageFormat::Pfm | ImageFormat::Exr) {
                        Depth::F32
                    } else {
                        Depth::U8
                    },
                },
            )
            .unwrap();
            let err = encode_image(&image, format).unwrap_err();
            assert!(err.to_string().contains("zero-area"), "{err}");
        }
    }

    #[test]
    fn write_and_read_files() {
        let dir = scratch("files");
        let image = test_image(6, 5, Channels::Rgba, Depth::U16);
        let path = dir.join("out.png");
        write_image(&path, &image).unwrap();
        assert_eq!(read_image(&path, &DecodeLimits::default()).unwrap(), image);
        assert_eq!(files_in(&dir), ["out.png"]);

        let err = write_image(&dir.join("out.bmp"), &image).unwrap_err();
        assert!(matches!(err, ImageIoError::UnknownFormat { .. }));
        let err = write_image(&dir.join("out.pfm"), &image).unwrap_err();
        assert!(err.to_string().contains("out.pfm"), "{err}");
        let err = read_image(&dir.join("missing.png"), &DecodeLimits::default()).unwrap_err();
        assert!(matches!(err, ImageIoError::Io { .. }));
        assert!(err.to_string().contains("missing.png"), "{err}");
        assert_eq!(files_in(&dir), ["out.png"]);
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn atomic_write_replaces_and_leaves_no_temp_files() {
        let dir = scratch("atomic");
        let path = dir.join("data.bin");
        write_atomic(&path, b"first version, longer").unwrap();
        write_atomic(&path, b"second").unwrap();
        assert_eq!(fs::read(&path).unwrap(), b"second");
        assert_eq!(files_in(&dir), ["data.bin"]);

        // A failing writer leaves the old content and no temp file behind.
        let err = write_atomic_with(&path, |w| {
            w.write_all(b"partial")?;
            Err(io::Error::other("boom"))
        })
        .unwrap_err();
        assert_eq!(err.to_string(), "boom");
        assert_eq!(fs::read(&path).unwrap(), b"second");
        assert_eq!(files_in(&dir), ["data.bin"]);

        // Streaming writes go through.
        write_atomic_with(&path, |w| {
            for i in 0..1000u32 {
                w.write_all(&i.to_le_bytes())?;
            }
            Ok(())
        })
        .unwrap();
        assert_eq!(fs::read(&path).unwrap().len(), 4000);

        assert!(write_atomic(&dir.join("no/such/dir/x"), b"x").is_err());
        assert!(write_atomic(Path::new("/"), b"x").is_err());
        assert_eq!(files_in(&dir), ["data.bin"]);
        fs::remove_dir_all(&dir).unwrap();
    }
}
