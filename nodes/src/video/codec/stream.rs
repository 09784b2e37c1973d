//! The sequence coder: I- and P-frames of 16×16 macroblocks into one bitstream, and its
//! decoder.
//!
//! # Bitstream (version 1), MSB first
//!
//! ```text
//! header   "OCVC"  u8 version=1  u16 width  u16 height  u32 frames
//!          u64 quantizer (IEEE-754 f64 bits)  u8 matrix (0 jpeg, 1 flat)      — 22 bytes
//! frame    1 bit type (0 = I, 1 = P), then every macroblock in raster order:
//!   I MB   4 blocks (TL, TR, BL, BR): se(DC − previous block's DC) (the predictor starts at
//!          0 each frame), then the AC pairs from scan position 1 and an end-of-block
//!   P MB   se(mvx − left mvx), se(mvy − left mvy) (left = (0, 0) at a row start),
//!          4 bits coded-block pattern (TL, TR, BL, BR), then each coded block's pairs from
//!          scan position 0 and an end-of-block
//! end      zero bits to the byte boundary
//! ```
//!
//! Blocks code `levels` of the DCT of the level-shifted samples (`x − 128`, I) or of the
//! residual against the motion-compensated prediction (P). The (run, level) code is
//! [`write_block`]. Frames are padded to multiples of 16 by repeating the last column and row;
//! the padded area is coded too and cropped away after decoding. The encoder predicts P-frames
//! from its own reconstruction (closed loop), which the decoder rebuilds bit for bit.

use rayon::prelude::*;

use crate::video::block_match::{SearchMethod, match_block};
use crate::video::gray::Plane;

use super::bits::{BitReader, BitWriter};
use super::block::{BlockCoder, N, read_block, write_block};

/// Macroblock side, px.
pub const MB: usize = 16;

/// Largest frame side accepted by the bitstream, px.
pub const MAX_SIDE: usize = 16384;

/// Largest frame count accepted by the bitstream.
pub const MAX_FRAMES: usize = 1 << 20;

/// Reported PSNR of a frame reconstructed without error, dB.
pub const PSNR_CAP_DB: f64 = 100.0;

/// Bitstream magic.
const MAGIC: &[u8; 4] = b"OCVC";

/// Bitstream version.
const VERSION: u32 = 1;

/// Header size, bits.
pub const HEADER_BITS: u64 = 22 * 8;

/// A u8 gray (luma) frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LumaFrame {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// `width × height` samples, row-major.
    pub data: Vec<u8>,
}

/// Coding settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CodecConfig {
    /// Flat-matrix quantizer step (the JPEG matrix is scaled by `quantizer / 16`).
    pub quantizer: f64,
    /// Flat quantization matrix instead of JPEG's luminance table.
    pub flat: bool,
    /// An I-frame every `gop` frames (1 = all intra).
    pub gop: usize,
    /// Motion search radius, px.
    pub search_px: usize,
    /// Motion search strategy.
    pub method: SearchMethod,
}

/// Frame type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameKind {
    /// Intra-coded.
    I,
    /// Motion-compensated from the previous decoded frame.
    P,
}

/// What one coded frame cost and how it came out.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameStats {
    /// I or P.
    pub kind: FrameKind,
    /// Bits of the frame's data (header excluded).
    pub bits: u64,
    /// PSNR of the reconstruction against the input, dB (peak 255), capped at
    /// [`PSNR_CAP_DB`].
    pub psnr_db: f64,
    /// Motion vectors `(dx, dy)` per macroblock, raster order (empty for I-frames): the
    /// prediction of the MB at (x, y) is the reference's block at (x + dx, y + dy).
    pub vectors: Vec<(i32, i32)>,
}

/// The result of [`encode`].
#[derive(Debug, Clone, PartialEq)]
pub struct Encoded {
    /// The bitstream.
    pub bytes: Vec<u8>,
    /// The encoder's reconstruction of every frame (what the decoder outputs).
    pub frames: Vec<LumaFrame>,
    /// Per frame: type, bits, PSNR, vectors.
    pub stats: Vec<FrameStats>,
}

/// Coded data of one macroblock.
#[derive(Debug, Clone)]
struct MbCode {
    mv: (i32, i32),
    /// Zig-zag levels of the 4 blocks.
    blocks: [[i32; N]; 4],
    /// Reconstructed 16×16 pixels.
    pixels: [u8; MB * MB],
}

/// `frame` padded to `pw × ph` by repeating its last column and row.
fn pad(frame: &LumaFrame, pw: usize, ph: usize) -> Vec<u8> {
    let (w, h) = (frame.width, frame.height);
    let mut out = vec![0u8; pw * ph];
    for (y, row) in out.chunks_exact_mut(pw).enumerate() {
        let src = &frame.data[y.min(h - 1) * w..][..w];
        row[..w].copy_from_slice(src);
        row[w..].fill(src[w - 1]);
    }
    out
}

/// The top-left `w × h` of a `pw`-wide padded plane.
fn crop(padded: &[u8], pw: usize, w: usize, h: usize) -> LumaFrame {
    let data = padded
        .chunks_exact(pw)
        .take(h)
        .flat_map(|row| row[..w].iter().copied())
        .collect();
    LumaFrame {
        width: w,
        height: h,
        data,
    }
}

/// The 8×8 block of a `pw`-wide plane at (x, y), as f64.
fn block_at(plane: &[u8], pw: usize, x: usize, y: usize) -> [f64; N] {
    let mut b = [0.0; N];
    for (r, row) in b.chunks_exact_mut(8).enumerate() {
        let src = &plane[(y + r) * pw + x..][..8];
        for (d, &s) in row.iter_mut().zip(src) {
            *d = f64::from(s);
        }
    }
    b
}

/// Offset of block `k` (0..4: TL, TR, BL, BR) inside its macroblock.
fn sub_offset(k: usize) -> (usize, usize) {
    ((k % 2) * 8, (k / 2) * 8)
}

/// Codes one macroblock: intra when `reference` is `None`, else motion-compensated.
#[allow(clippy::too_many_arguments)]
fn code_mb(
    coder: &BlockCoder,
    cur: &[u8],
    cur_plane: &Plane,
    reference: Option<(&[u8], &Plane)>,
    pw: usize,
    x0: usize,
    y0: usize,
    config: &CodecConfig,
) -> MbCode {
    let mv = match reference {
        Some((_, ref_plane)) => {
            let v = match_block(
                cur_plane,
                ref_plane,
                x0,
                y0,
                MB,
                config.search_px,
                config.method,
                false,
            );
            (v.dx as i32, v.dy as i32)
        }
        None => (0, 0),
    };
    let mut blocks = [[0i32; N]; 4];
    let mut pixels = [0u8; MB * MB];
    for (k, levels_out) in blocks.iter_mut().enumerate() {
        let (ox, oy) = sub_offset(k);
        let (bx, by) = (x0 + ox, y0 + oy);
        let samples = block_at(cur, pw, bx, by);
        let prediction = match reference {
            Some((ref_pixels, _)) => block_at(
                ref_pixels,
                pw,
                (bx as i64 + i64::from(mv.0)) as usize,
                (by as i64 + i64::from(mv.1)) as usize,
            ),
            None => [128.0; N],
        };
        let mut residual = [0.0; N];
        for ((r, &s), &p) in residual.iter_mut().zip(&samples).zip(&prediction) {
            *r = s - p;
        }
        let levels = coder.quantize(&residual);
        let recon = coder.reconstruct(&levels, &prediction);
        for (r, row) in recon.chunks_exact(8).enumerate() {
            pixels[(oy + r) * MB + ox..][..8].copy_from_slice(row);
        }
        *levels_out = coder.scan(&levels);
    }
    MbCode { mv, blocks, pixels }
}

fn plane_of(data: &[u8], pw: usize, ph: usize) -> Plane {
    Plane {
        width: pw,
        height: ph,
        data: data.iter().map(|&v| f32::from(v)).collect(),
    }
}

/// Mean squared error of two equal-length sample vectors.
fn mse(a: &[u8], b: &[u8]) -> f64 {
    let sum: u64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| {
            let d = i64::from(x) - i64::from(y);
            (d * d) as u64
        })
        .sum();
    sum as f64 / a.len().max(1) as f64
}

/// PSNR (peak 255) of `mse`, capped at [`PSNR_CAP_DB`].
pub fn psnr_capped(mse: f64) -> f64 {
    crate::analyze::quality::psnr_db(mse, 255.0)
        .unwrap_or(PSNR_CAP_DB)
        .min(PSNR_CAP_DB)
}

/// Checks the settings; the message names the parameter.
pub fn check_config(config: &CodecConfig) -> Result<(), String> {
    if !(config.quantizer.is_finite() && (0.05..=1024.0).contains(&config.quantizer)) {
        return Err(format!(
            "`quantizer` must be in [0.05, 1024], got {}",
            config.quantizer
        ));
    }
    if config.gop == 0 {
        return Err("`gop` must be at least 1".into());
    }
    if config.search_px > 256 {
        return Err(format!(
            "`search_px` must be at most 256, got {}",
            config.search_px
        ));
    }
    Ok(())
}

/// Encodes `frames` (all the same size, at least one) into a bitstream; see the module docs
/// for the format. Returns the bytes, the reconstruction and per-frame statistics.
pub fn encode(frames: &[LumaFrame], config: &CodecConfig) -> Result<Encoded, String> {
    check_config(config)?;
    let first = frames
        .first()
        .ok_or_else(|| "needs at least one frame".to_string())?;
    let (w, h) = (first.width, first.height);
    if w == 0 || h == 0 || w > MAX_SIDE || h > MAX_SIDE {
        return Err(format!(
            "frames must be 1..={MAX_SIDE} px on each side, got {w}×{h}"
        ));
    }
    if frames.len() > MAX_FRAMES {
        return Err(format!("at most {MAX_FRAMES} frames, got {}", frames.len()));
    }
    for (i, f) in frames.iter().enumerate() {
        if (f.width, f.height) != (w, h) || f.data.len() != w * h {
            return Err(format!(
                "frame {i} is {}×{} but frame 0 is {w}×{h}: all frames must have one size",
                f.width, f.height
            ));
        }
    }
    let (pw, ph) = (w.div_ceil(MB) * MB, h.div_ceil(MB) * MB);
    let (cols, rows) = (pw / MB, ph / MB);
    let coder = BlockCoder::new(config.quantizer, config.flat);
    let mut writer = BitWriter::new();
    for &b in MAGIC {
        writer.put_bits(u32::from(b), 8);
    }
    writer.put_bits(VERSION, 8);
    writer.put_bits(w as u32, 16);
    writer.put_bits(h as u32, 16);
    writer.put_bits(frames.len() as u32, 32);
    let q = config.quantizer.to_bits();
    writer.put_bits((q >> 32) as u32, 32);
    writer.put_bits(q as u32, 32);
    writer.put_bits(u32::from(config.flat), 8);

    let mut reference: Option<Vec<u8>> = None;
    let mut out_frames = Vec::with_capacity(frames.len());
    let mut stats = Vec::with_capacity(frames.len());
    for (t, frame) in frames.iter().enumerate() {
        let kind = if t % config.gop == 0 {
            FrameKind::I
        } else {
            FrameKind::P
        };
        let cur = pad(frame, pw, ph);
        let cur_plane = plane_of(&cur, pw, ph);
        let ref_plane = match (kind, &reference) {
            (FrameKind::P, Some(r)) => Some(plane_of(r, pw, ph)),
            _ => None,
        };
        let ref_pair = match (&reference, &ref_plane) {
            (Some(r), Some(p)) => Some((r.as_slice(), p)),
            _ => None,
        };
        // Macroblock rows in parallel; each MB's coding is a pure function of its inputs.
        let mbs: Vec<MbCode> = (0..rows)
            .into_par_iter()
            .flat_map_iter(|my| {
                let cur = &cur;
                let cur_plane = &cur_plane;
                let coder = &coder;
                (0..cols).map(move |mx| {
                    code_mb(
                        coder,
                        cur,
                        cur_plane,
                        ref_pair,
                        pw,
                        mx * MB,
                        my * MB,
                        config,
                    )
                })
            })
            .collect();
        let start_bits = writer.bit_len();
        writer.put_bit(kind == FrameKind::P);
        let mut recon = vec![0u8; pw * ph];
        let mut dc_pred = 0i32;
        for (i, mb) in mbs.iter().enumerate() {
            let (mx, my) = (i % cols, i / cols);
            match kind {
                FrameKind::I => {
                    for levels in &mb.blocks {
                        writer.put_se(levels[0] - dc_pred);
                        dc_pred = levels[0];
                        write_block(&mut writer, levels, 1);
                    }
                }
                FrameKind::P => {
                    let left = if mx == 0 { (0, 0) } else { mbs[i - 1].mv };
                    writer.put_se(mb.mv.0 - left.0);
                    writer.put_se(mb.mv.1 - left.1);
                    for levels in &mb.blocks {
                        writer.put_bit(levels.iter().any(|&l| l != 0));
                    }
                    for levels in &mb.blocks {
                        if levels.iter().any(|&l| l != 0) {
                            write_block(&mut writer, levels, 0);
                        }
                    }
                }
            }
            for (r, row) in mb.pixels.chunks_exact(MB).enumerate() {
                recon[(my * MB + r) * pw + mx * MB..][..MB].copy_from_slice(row);
            }
        }
        let bits = writer.bit_len() - start_bits;
        let cropped = crop(&recon, pw, w, h);
        stats.push(FrameStats {
            kind,
            bits,
            psnr_db: psnr_capped(mse(&cropped.data, &frame.data)),
            vectors: if kind == FrameKind::P {
                mbs.iter().map(|m| m.mv).collect()
            } else {
                Vec::new()
            },
        });
        out_frames.push(cropped);
        reference = Some(recon);
    }
    Ok(Encoded {
        bytes: writer.finish(),
        frames: out_frames,
        stats,
    })
}

/// A decoded bitstream.
#[derive(Debug, Clone, PartialEq)]
pub struct Decoded {
    /// The frames, cropped to the coded size.
    pub frames: Vec<LumaFrame>,
    /// Per frame: type and bits read.
    pub kinds: Vec<(FrameKind, u64)>,
    /// Quantizer read from the header.
    pub quantizer: f64,
    /// Flat matrix flag read from the header.
    pub flat: bool,
}

/// Decodes a bitstream of [`encode`]. Every malformed or truncated stream is an error message
/// (never a panic); trailing bytes beyond the last frame's padding are an error too.
pub fn decode(bytes: &[u8]) -> Result<Decoded, String> {
    let mut r = BitReader::new(bytes);
    let header = |r: &mut BitReader<'_>, n: u32| {
        r.bits(n)
            .map_err(|_| "the bitstream is shorter than its 22-byte header".to_string())
    };
    let mut magic = [0u8; 4];
    for m in &mut magic {
        *m = header(&mut r, 8)? as u8;
    }
    if &magic != MAGIC {
        return Err(format!(
            "not an Ocellus video bitstream: the first bytes are {magic:?}, expected \"OCVC\""
        ));
    }
    let version = header(&mut r, 8)?;
    if version != VERSION {
        return Err(format!(
            "unsupported bitstream version {version} (this decoder reads version {VERSION})"
        ));
    }
    let w = header(&mut r, 16)? as usize;
    let h = header(&mut r, 16)? as usize;
    let n_frames = header(&mut r, 32)? as usize;
    let q_hi = u64::from(header(&mut r, 32)?);
    let q_lo = u64::from(header(&mut r, 32)?);
    let quantizer = f64::from_bits((q_hi << 32) | q_lo);
    let matrix = header(&mut r, 8)?;
    if w == 0 || h == 0 || w > MAX_SIDE || h > MAX_SIDE {
        return Err(format!(
            "corrupt header: frame size {w}×{h} (each side must be 1..={MAX_SIDE})"
        ));
    }
    if n_frames == 0 || n_frames > MAX_FRAMES {
        return Err(format!(
            "corrupt header: {n_frames} frames (must be 1..={MAX_FRAMES})"
        ));
    }
    if matrix > 1 {
        return Err(format!(
            "corrupt header: quantization matrix code {matrix} (0 jpeg, 1 flat)"
        ));
    }
    let flat = matrix == 1;
    check_config(&CodecConfig {
        quantizer,
        flat,
        gop: 1,
        search_px: 0,
        method: SearchMethod::Full,
    })
    .map_err(|e| format!("corrupt header: {e}"))?;
    let (pw, ph) = (w.div_ceil(MB) * MB, h.div_ceil(MB) * MB);
    let (cols, rows) = (pw / MB, ph / MB);
    // Every frame needs at least 1 + 6 bits per macroblock: refuse before allocating.
    let min_bits = (n_frames as u64).saturating_mul(1 + 6 * (cols * rows) as u64);
    if min_bits > r.remaining() {
        return Err(format!(
            "the bitstream is truncated: {n_frames} frames of {w}×{h} need at least {min_bits} \
             bits, {} are left",
            r.remaining()
        ));
    }
    let coder = BlockCoder::new(quantizer, flat);
    let mut reference: Option<Vec<u8>> = None;
    let mut frames = Vec::with_capacity(n_frames);
    let mut kinds = Vec::with_capacity(n_frames);
    for t in 0..n_frames {
        let start = r.position();
        let at = |e: String| format!("frame {t}: {e}");
        let kind = if r.bit().map_err(at)? {
            FrameKind::P
        } else {
            FrameKind::I
        };
        if kind == FrameKind::P && reference.is_none() {
            return Err(format!(
                "corrupt bitstream: frame {t} is a P-frame with no frame before it"
            ));
        }
        let mut recon = vec![0u8; pw * ph];
        let mut dc_pred = 0i32;
        for my in 0..rows {
            let mut left = (0i32, 0i32);
            for mx in 0..cols {
                let (x0, y0) = (mx * MB, my * MB);
                let mut pixels = [0u8; MB * MB];
                match (kind, &reference) {
                    (FrameKind::P, Some(ref_pixels)) => {
                        let dx = left.0.saturating_add(r.se().map_err(at)?);
                        let dy = left.1.saturating_add(r.se().map_err(at)?);
                        left = (dx, dy);
                        let (rx, ry) = (x0 as i64 + i64::from(dx), y0 as i64 + i64::from(dy));
                        if rx < 0 || ry < 0 || rx as usize + MB > pw || ry as usize + MB > ph {
                            return Err(format!(
                                "corrupt bitstream: frame {t}, macroblock ({mx}, {my}): motion \
                                 vector ({dx}, {dy}) points outside the reference frame"
                            ));
                        }
                        let mut coded = [false; 4];
                        for c in &mut coded {
                            *c = r.bit().map_err(at)?;
                        }
                        for (k, &is_coded) in coded.iter().enumerate() {
                            let (ox, oy) = sub_offset(k);
                            let scanned = if is_coded {
                                read_block(&mut r, 0).map_err(at)?
                            } else {
                                [0; N]
                            };
                            let prediction =
                                block_at(ref_pixels, pw, rx as usize + ox, ry as usize + oy);
                            let recon = coder.reconstruct(&coder.unscan(&scanned), &prediction);
                            for (row, src) in recon.chunks_exact(8).enumerate() {
                                pixels[(oy + row) * MB + ox..][..8].copy_from_slice(src);
                            }
                        }
                    }
                    _ => {
                        for k in 0..4 {
                            let (ox, oy) = sub_offset(k);
                            let dc = dc_pred.saturating_add(r.se().map_err(at)?);
                            if dc.unsigned_abs() > super::block::MAX_LEVEL as u32 {
                                return Err(format!(
                                    "corrupt bitstream: frame {t}: DC level {dc} out of range"
                                ));
                            }
                            dc_pred = dc;
                            let mut scanned = read_block(&mut r, 1).map_err(at)?;
                            scanned[0] = dc;
                            let recon = coder.reconstruct(&coder.unscan(&scanned), &[128.0; N]);
                            for (row, src) in recon.chunks_exact(8).enumerate() {
                                pixels[(oy + row) * MB + ox..][..8].copy_from_slice(src);
                            }
                        }
                    }
                }
                for (row, src) in pixels.chunks_exact(MB).enumerate() {
                    recon[(y0 + row) * pw + x0..][..MB].copy_from_slice(src);
                }
            }
        }
        kinds.push((kind, r.position() - start));
        frames.push(crop(&recon, pw, w, h));
        reference = Some(recon);
    }
    if r.remaining() >= 8 {
        return Err(format!(
            "corrupt bitstream: {} bytes follow the last frame",
            r.remaining() / 8
        ));
    }
    Ok(Decoded {
        frames,
        kinds,
        quantizer,
        flat,
    })
}
