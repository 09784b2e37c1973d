//! `video.encode`, `video.decode`, `video.write_bitstream`, `video.read_bitstream`: a small
//! block-based hybrid video codec (8×8 DCT, JPEG-style quantization, zig-zag run-length
//! coding with Exp-Golomb codes, I-frames and motion-compensated P-frames on 16×16
//! macroblocks).
//!
//! The algorithms are [`stream::encode`] and [`stream::decode`] (format in [`stream`]); the
//! block layer is [`block`], the bit layer [`bits`]. The operators are thin wrappers.
//!
//! # Why the bitstream is a Matrix
//! The engine has no byte-blob port type. The bitstream travels between nodes as an `n × 1`
//! Matrix of byte values 0–255 (exact in f64): pure and cacheable like every other value, so
//! `video.decode` can check the round trip inside a graph, while writing a file is the separate
//! side-effect operator `video.write_bitstream` (temp file + rename, like `io.write_image`),
//! with `video.read_bitstream` to load one back.
//!
//! # Determinism
//! Macroblock rows are coded in parallel, each macroblock by the same sequential f64
//! arithmetic whatever thread runs it, and the bits are written in raster order afterwards, so
//! the bitstream and the reconstruction are bit-identical for any thread count.

pub mod bits;
pub mod block;
pub mod stream;

use std::path::PathBuf;
use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Matrix, Metrics, PixelData, Value};
use ocellus_engine::{param_enum, params};

use crate::video::block_match::SearchMethod;
use crate::video::gray::gray_f32;
use stream::{CodecConfig, FrameKind, LumaFrame, decode, encode};

param_enum! {
    /// Quantization matrix of `video.encode`.
    pub enum QuantMatrix {
        /// JPEG's luminance table (ITU-T T.81 Table K.1) scaled by `quantizer / 16`: coarser
        /// steps for high frequencies.
        Jpeg = "jpeg",
        /// The same step `quantizer` for every coefficient.
        Flat = "flat",
    }
}

params! {
    /// Parameters of `video.encode`.
    pub struct EncodeParams {
        /// Quantizer step, in DCT units of 8-bit levels, 0.05..=1024: the step of every
        /// coefficient with the flat matrix, of the DC (and 16/16 entries) with the JPEG one
        /// (which is scaled by `quantizer / 16`, so 16 is JPEG's quality-50 table). Smaller is
        /// finer: more bits, higher PSNR. Default 16.
        quantizer: f64 = 16.0,
        /// Quantization matrix: "jpeg" (luminance table) or "flat". Default "jpeg".
        matrix: QuantMatrix = QuantMatrix::Jpeg,
        /// Group of pictures: an I-frame every `gop` frames, P-frames between; 1 = all intra.
        /// 1..=10000. Default 12.
        gop: u32 = 12,
        /// Motion search radius, px, 0..=256 (0 = no motion, frame difference coding).
        /// Default 8.
        search_px: u32 = 8,
        /// Motion search: "full" (every integer vector within `search_px`) or
        /// "coarse_to_fine" (three-step search: ~9 log₂(search_px) candidates; faster, may
        /// miss the best vector). Default "full".
        search: SearchMethod = SearchMethod::Full,
    }
}

/// Block-based video encoder (`video.encode`). See [`stream::encode`].
#[derive(Debug, Clone, PartialEq)]
pub struct Encode {
    config: CodecConfig,
}

const MAX_GOP: u32 = 10_000;

impl Op for Encode {
    type Params = EncodeParams;
    const ID: &'static str = "video.encode";
    const SUMMARY: &'static str = "Encodes frames with a block-based hybrid codec (8×8 DCT, motion-compensated P-frames) into a bitstream.";
    const DOC: &'static str = r#"
A small MPEG-1/H.261-style hybrid codec of the luma (colour frames are converted by BT.601,
u16 / 257, f32 · 255; each frame rounded to 8 bits):

- Frames are padded to multiples of 16 by repeating the last column and row, cut into 16×16
  macroblocks of four 8×8 blocks, and cropped back after decoding.
- I-frame (every `gop` frames): each block's samples minus 128 go through the orthonormal 8×8
  DCT-II, are quantized with step `quantizer · Q[k] / 16` (Q = JPEG's luminance table, or 16
  for `matrix: "flat"`), rounded to the nearest level; the DC is coded as the difference to
  the previous block's DC.
- P-frame: each macroblock's motion vector into the previous *decoded* frame (closed loop, so
  the decoder does not drift) is found by SAD block matching within ±`search_px` (full or
  three-step search, the `video.block_match` search), coded as the difference to the left
  macroblock's vector; the residual against the motion-compensated block is DCT-coded with the
  same quantizer; a 4-bit coded-block pattern skips all-zero blocks.
- Levels are scanned in zig-zag order and coded as (run, level) pairs with an end-of-block,
  every symbol an order-0 Exp-Golomb code (`ue(run + 1)`, `ue(|level| − 1)`, sign bit;
  `ue(0)` = end of block): real bits, written MSB first after a 22-byte header.

Outputs: `bitstream`, an n × 1 Matrix of the stream's bytes (0–255) for `video.decode` /
`video.write_bitstream`; `frames`, the encoder's reconstruction (u8 gray, what the decoder
returns, bit for bit); `per_frame`, one row `[frame, type (0 = I, 1 = P), bits, bpp,
psnr_db, mean |motion vector| px]` per frame (bits of the frame's data, bpp over the
uncropped frame size, PSNR against the input luma with peak 255, capped at 100 dB for an
exact frame); `metrics`: bits (whole stream, header included), bytes, bpp, psnr_mean_db,
psnr_min_db, i_frames, p_frames, i_bits_mean, p_bits_mean.

Reference: ITU-T H.261 (1990) and ISO/IEC 11172-2 (MPEG-1 video) for the hybrid
DCT/motion-compensation scheme; ITU-T T.81 (JPEG) for the DCT, quantization table and
zig-zag scan; ITU-T H.264 §9.1 for Exp-Golomb codes; T. Koga et al., NTC 1981 (three-step
search).

Example:
    "enc": (op: "video.encode", inputs: { "frames": "clip.frames" }, params: (quantizer: 16.0, gop: 12, search_px: 8, search: "full")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "frames",
            PortType::Image.list_of(),
            "Frames in time order, one size, any pixel format (luma is coded).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "bitstream",
                PortType::Matrix,
                "The bitstream: n × 1 matrix of byte values 0–255.",
            ),
            PortSpec::new(
                "frames",
                PortType::Image.list_of(),
                "The encoder's reconstruction, u8 gray, input size.",
            ),
            PortSpec::new(
                "per_frame",
                PortType::Matrix,
                "One row [frame, type (0 I, 1 P), bits, bpp, psnr_db, mean |mv| px] per frame.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "bits, bytes, bpp, psnr_mean_db, psnr_min_db, i_frames, p_frames, i_bits_mean, p_bits_mean.",
            ),
        ]
    }

    fn new(params: EncodeParams) -> Result<Self, String> {
        let EncodeParams {
            quantizer,
            matrix,
            gop,
            search_px,
            search,
        } = params;
        if !(1..=MAX_GOP).contains(&gop) {
            return Err(format!("`gop` must be in 1..={MAX_GOP}, got {gop}"));
        }
        let config = CodecConfig {
            quantizer,
            flat: matrix == QuantMatrix::Flat,
            gop: gop as usize,
            search_px: search_px as usize,
            method: search,
        };
        stream::check_config(&config)?;
        Ok(Encode { config })
    }
}

impl Operator for Encode {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let frames = luma_frames(inputs.require("frames")?)?;
        let encoded = encode(&frames, &self.config).map_err(|e| OpError::input("frames", e))?;
        let (w, h) = (frames[0].width, frames[0].height);
        let pixels = (w * h) as f64;
        let mut rows = Vec::with_capacity(encoded.stats.len() * 6);
        for (t, s) in encoded.stats.iter().enumerate() {
            let mean_mv = if s.vectors.is_empty() {
                0.0
            } else {
                s.vectors
                    .iter()
                    .map(|&(dx, dy)| f64::from(dx).hypot(f64::from(dy)))
                    .sum::<f64>()
                    / s.vectors.len() as f64
            };
            rows.extend([
                t as f64,
                f64::from(u8::from(s.kind == FrameKind::P)),
                s.bits as f64,
                s.bits as f64 / pixels,
                s.psnr_db,
                mean_mv,
            ]);
        }
        let n = encoded.stats.len() as f64;
        let total_bits = encoded.bytes.len() as f64 * 8.0;
        let mean_bits = |kind: FrameKind| {
            let b: Vec<f64> = encoded
                .stats
                .iter()
                .filter(|s| s.kind == kind)
                .map(|s| s.bits as f64)
                .collect();
            (
                b.len() as f64,
                b.iter().sum::<f64>() / b.len().max(1) as f64,
            )
        };
        let (n_i, i_bits) = mean_bits(FrameKind::I);
        let (n_p, p_bits) = mean_bits(FrameKind::P);
        let mut metrics = Metrics::new();
        metrics.insert("bits".into(), total_bits);
        metrics.insert("bytes".into(), encoded.bytes.len() as f64);
        metrics.insert("bpp".into(), total_bits / (pixels * n));
        metrics.insert(
            "psnr_mean_db".into(),
            encoded.stats.iter().map(|s| s.psnr_db).sum::<f64>() / n,
        );
        metrics.insert(
            "psnr_min_db".into(),
            encoded
                .stats
                .iter()
                .map(|s| s.psnr_db)
                .fold(f64::INFINITY, f64::min),
        );
        metrics.insert("i_frames".into(), n_i);
        metrics.insert("p_frames".into(), n_p);
        metrics.insert("i_bits_mean".into(), i_bits);
        metrics.insert("p_bits_mean".into(), p_bits);
        Ok(Outputs::new()
            .with("bitstream", bytes_value(&encoded.bytes)?)
            .with("frames", frames_value(encoded.frames)?)
            .with("per_frame", matrix_value(encoded.stats.len(), 6, rows)?)
            .with("metrics", Value::metrics(metrics)))
    }
}

params! {
    /// Parameters of `video.decode` (none: everything is in the bitstream).
    pub struct DecodeParams {}
}

/// Decoder of `video.encode`'s bitstream (`video.decode`). See [`stream::decode`].
#[derive(Debug, Clone, PartialEq)]
pub struct Decode;

impl Op for Decode {
    type Params = DecodeParams;
    const ID: &'static str = "video.decode";
    const SUMMARY: &'static str = "Decodes a `video.encode` bitstream back into frames.";
    const DOC: &'static str = r#"
Reads the bitstream of `video.encode` (format in the `video.encode` documentation and the
`nodes/src/video/codec/stream.rs` module docs) and rebuilds every frame from it alone: I-blocks
by inverse DCT of the dequantized levels plus 128, P-macroblocks by copying the previous
decoded frame's block at the motion vector and adding the inverse-DCT residual. The frames
equal the encoder's `frames` output bit for bit.

A truncated or corrupt stream (wrong magic or version, impossible header, a run past the end
of a block, a motion vector outside the frame, trailing bytes, a byte matrix entry that is not
an integer 0–255) is an error naming what is wrong; nothing panics.

Outputs: `frames` (u8 gray, the coded size), `per_frame` (one row `[frame, type (0 I, 1 P),
bits, bpp]` per frame, read from the stream) and `metrics` (frames, width, height, bits, bpp,
quantizer).

Reference: see `video.encode`.

Example:
    "dec": (op: "video.decode", inputs: { "bitstream": "enc.bitstream" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "bitstream",
            PortType::Matrix,
            "Bytes of a `video.encode` bitstream (n × 1 or 1 × n, entries 0–255).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "frames",
                PortType::Image.list_of(),
                "Decoded frames, u8 gray.",
            ),
            PortSpec::new(
                "per_frame",
                PortType::Matrix,
                "One row [frame, type (0 I, 1 P), bits, bpp] per frame.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "frames, width, height, bits, bpp, quantizer.",
            ),
        ]
    }

    fn new(_params: DecodeParams) -> Result<Self, String> {
        Ok(Decode)
    }
}

impl Operator for Decode {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let bytes = matrix_bytes(inputs.require("bitstream")?)?;
        let decoded = decode(&bytes).map_err(|e| OpError::input("bitstream", e))?;
        let (w, h) = decoded
            .frames
            .first()
            .map(|f| (f.width, f.height))
            .unwrap_or((0, 0));
        let pixels = (w * h).max(1) as f64;
        let rows = decoded
            .kinds
            .iter()
            .enumerate()
            .flat_map(|(t, &(kind, bits))| {
                [
                    t as f64,
                    f64::from(u8::from(kind == FrameKind::P)),
                    bits as f64,
                    bits as f64 / pixels,
                ]
            })
            .collect();
        let n = decoded.frames.len();
        let mut metrics = Metrics::new();
        metrics.insert("frames".into(), n as f64);
        metrics.insert("width".into(), w as f64);
        metrics.insert("height".into(), h as f64);
        metrics.insert("bits".into(), bytes.len() as f64 * 8.0);
        metrics.insert(
            "bpp".into(),
            bytes.len() as f64 * 8.0 / (pixels * n.max(1) as f64),
        );
        metrics.insert("quantizer".into(), decoded.quantizer);
        Ok(Outputs::new()
            .with("per_frame", matrix_value(n, 4, rows)?)
            .with("frames", frames_value(decoded.frames)?)
            .with("metrics", Value::metrics(metrics)))
    }
}

params! {
    /// Parameters of `video.write_bitstream`.
    pub struct WriteBitstreamParams {
        /// Destination file (any extension; `.ocv` suggested). Relative paths resolve against
        /// the graph file's folder. Required.
        path: PathBuf = PathBuf::new(),
    }
}

/// Writes a bitstream Matrix to a file atomically (`video.write_bitstream`).
#[derive(Debug, Clone, PartialEq)]
pub struct WriteBitstream {
    path: PathBuf,
}

impl Op for WriteBitstream {
    type Params = WriteBitstreamParams;
    const ID: &'static str = "video.write_bitstream";
    const SUMMARY: &'static str = "Writes a `video.encode` bitstream to a file, atomically.";
    const DOC: &'static str = r#"
Writes the bytes of a bitstream Matrix (n × 1 or 1 × n, entries integers 0–255, as
`video.encode` outputs) to `path` through a temporary file in the same folder that is synced
and renamed into place, so readers see the old file or the complete new one (the engine's
`write_atomic`, as `io.write_image`). A side effect: runs whenever the graph runs, never
cached. Read back with `video.read_bitstream`.

Example:
    "save": (op: "video.write_bitstream", inputs: { "bitstream": "enc.bitstream" }, params: (path: "out/clip.ocv")),
"#;
    const SIDE_EFFECTS: bool = true;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "bitstream",
            PortType::Matrix,
            "Bytes, entries 0–255.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("path", PortType::Text, "The file written.")]
    }

    fn new(params: WriteBitstreamParams) -> Result<Self, String> {
        if params.path.as_os_str().is_empty() {
            return Err("`path` is required".into());
        }
        Ok(WriteBitstream { path: params.path })
    }
}

impl Operator for WriteBitstream {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let bytes = matrix_bytes(inputs.require("bitstream")?)?;
        ocellus_engine::image_io::write_atomic(&self.path, &bytes)
            .map_err(|e| OpError::io(&self.path, e))?;
        Ok(Outputs::new().with("path", Value::Text(self.path.to_string_lossy().into())))
    }
}

params! {
    /// Parameters of `video.read_bitstream`.
    pub struct ReadBitstreamParams {
        /// File to read. Relative paths resolve against the graph file's folder. Required.
        path: PathBuf = PathBuf::new(),
    }
}

/// Reads a bitstream file into a byte Matrix (`video.read_bitstream`).
#[derive(Debug, Clone, PartialEq)]
pub struct ReadBitstream {
    path: PathBuf,
}

/// Largest bitstream file read, bytes.
const MAX_FILE_BYTES: u64 = 1 << 30;

impl Op for ReadBitstream {
    type Params = ReadBitstreamParams;
    const ID: &'static str = "video.read_bitstream";
    const SUMMARY: &'static str =
        "Reads a bitstream file into an n × 1 byte Matrix for `video.decode`.";
    const DOC: &'static str = r#"
Reads the file at `path` (at most 1 GiB) into an n × 1 Matrix of its bytes (0–255), the form
`video.decode` takes. The content is not checked here; `video.decode` does that.

Example:
    "load": (op: "video.read_bitstream", params: (path: "out/clip.ocv")),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "bitstream",
            PortType::Matrix,
            "The file's bytes, n × 1.",
        )]
    }

    fn new(params: ReadBitstreamParams) -> Result<Self, String> {
        if params.path.as_os_str().is_empty() {
            return Err("`path` is required".into());
        }
        Ok(ReadBitstream { path: params.path })
    }
}

impl Operator for ReadBitstream {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let len = std::fs::metadata(&self.path)
            .map_err(|e| OpError::io(&self.path, e))?
            .len();
        if len > MAX_FILE_BYTES {
            return Err(OpError::io(
                &self.path,
                format!("is {len} bytes, more than the 1 GiB limit"),
            ));
        }
        let bytes = ocellus_engine::limits::read_file(&self.path)
            .map_err(|e| OpError::io(&self.path, e))?;
        Ok(Outputs::new().with("bitstream", bytes_value(&bytes)?))
    }
}

/// Registers the codec operators.
pub fn register(
    registry: &mut ocellus_engine::op::Registry,
) -> Result<(), ocellus_engine::op::RegistryError> {
    registry.register::<Encode>()?;
    registry.register::<Decode>()?;
    registry.register::<WriteBitstream>()?;
    registry.register::<ReadBitstream>()
}

/// The luma of every frame of a `List<Image>`, rounded to u8; errors name the port.
pub fn luma_frames(value: &Value) -> Result<Vec<LumaFrame>, OpError> {
    let Value::List(list) = value else {
        return Err(OpError::input("frames", "expected a list of images"));
    };
    if list.items.is_empty() {
        return Err(OpError::input("frames", "needs at least one frame"));
    }
    list.items
        .iter()
        .enumerate()
        .map(|(i, item)| {
            let Value::Image(image) = item else {
                return Err(OpError::input(
                    "frames",
                    format!("item {i} is not an image"),
                ));
            };
            luma_frame(image).map_err(|e| OpError::input("frames", format!("frame {i}: {e}")))
        })
        .collect()
}

/// The luma of one image, rounded to u8: u8 gray as is, otherwise [`gray_f32`].
pub fn luma_frame(image: &Image) -> Result<LumaFrame, String> {
    if image.width() == 0 || image.height() == 0 {
        return Err("is empty".into());
    }
    let data = match (image.channels(), image.data()) {
        (Channels::Gray, PixelData::U8(v)) => v.clone(),
        (_, PixelData::F32(v)) if v.iter().any(|s| !s.is_finite()) => {
            return Err("contains NaN or infinite samples".into());
        }
        _ => gray_f32(image)
            .data
            .iter()
            .map(|&s| s.round().clamp(0.0, 255.0) as u8)
            .collect(),
    };
    Ok(LumaFrame {
        width: image.width(),
        height: image.height(),
        data,
    })
}

/// The bytes of a byte Matrix; an error unless every entry is an integer 0–255.
pub fn matrix_bytes(value: &Value) -> Result<Vec<u8>, OpError> {
    let Value::Matrix(m) = value else {
        return Err(OpError::input("bitstream", "expected a Matrix of bytes"));
    };
    if m.cols != 1 && m.rows != 1 && !m.data.is_empty() {
        return Err(OpError::input(
            "bitstream",
            format!(
                "expected an n × 1 or 1 × n matrix of bytes, got {} × {}",
                m.rows, m.cols
            ),
        ));
    }
    m.data
        .iter()
        .enumerate()
        .map(|(i, &v)| {
            if v.fract() == 0.0 && (0.0..=255.0).contains(&v) {
                Ok(v as u8)
            } else {
                Err(OpError::input(
                    "bitstream",
                    format!("entry {i} is {v}, not a byte value 0–255"),
                ))
            }
        })
        .collect()
}

fn bytes_value(bytes: &[u8]) -> Result<Value, OpError> {
    matrix_value(
        bytes.len(),
        1,
        bytes.iter().map(|&b| f64::from(b)).collect(),
    )
}

fn matrix_value(rows: usize, cols: usize, data: Vec<f64>) -> Result<Value, OpError> {
    Matrix::new(rows, cols, data)
        .map(|m| Value::Matrix(Arc::new(m)))
        .map_err(|e| OpError::failed(e.to_string()))
}

fn frames_value(frames: Vec<LumaFrame>) -> Result<Value, OpError> {
    let items = frames
        .into_iter()
        .map(|f| {
            Image::from_u8(f.width, f.height, Channels::Gray, f.data)
                .map(Value::image)
                .map_err(|e| OpError::failed(e.to_string()))
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Value::list(PortType::Image, items))
}

#[cfg(test)]
mod tests;
