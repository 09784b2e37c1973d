//! `filter.equalize` and `filter.clahe`: global histogram equalization and contrast-limited
//! adaptive histogram equalization, with OpenCV's `equalizeHist` and `CLAHE` arithmetic.
//!
//! [`equalize`] maps every sample through the scaled cumulative histogram; [`clahe`] builds one
//! clipped, equalizing lookup table per tile and blends the four nearest tables bilinearly.
//! Colour images are equalized through their luma (the default) or channel by channel.
//!
//! How it runs:
//! - Histograms are counted in parallel fixed-size chunks (see
//!   [`crate::analyze::histogram`]); CLAHE's tile tables are built in parallel, one per tile,
//!   and its interpolation runs over fixed bands of rows. Results are identical for any thread
//!   count.
//! - The lookup tables use OpenCV's f32 arithmetic (`saturate_cast<uchar>(sum · scale)`, round
//!   half to even), so u8 results match `cv2.equalizeHist` and `cv2.createCLAHE(...).apply`.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::border::{BorderMode, map_index};
use crate::analyze::histogram::{histogram_u8, histogram_u16};

/// Rows per parallel band of the CLAHE interpolation.
const BAND_ROWS: usize = 32;

/// Largest number of CLAHE tiles along an axis.
pub const MAX_TILES: u32 = 256;

param_enum! {
    /// How colour images are equalized.
    pub enum ColorMode {
        /// Equalize the luma Y of YCbCr (BT.601 weights, OpenCV's `RGB2YCrCb` fixed point) and
        /// shift R, G and B by the luma change, which keeps Cb and Cr: hues are preserved.
        Luma = "luma",
        /// Equalize R, G and B independently (can shift hues). Alpha is never changed.
        PerChannel = "per_channel",
    }
}

params! {
    /// Parameters of `filter.equalize`.
    pub struct EqualizeParams {
        /// Colour images: "luma" (default, hue-preserving) or "per_channel". Ignored for gray.
        mode: ColorMode = ColorMode::Luma,
    }
}

/// Histogram equalization (`filter.equalize`). See [`equalize`].
#[derive(Debug, Clone, PartialEq)]
pub struct Equalize {
    mode: ColorMode,
}

impl Op for Equalize {
    type Params = EqualizeParams;
    const ID: &'static str = "filter.equalize";
    const SUMMARY: &'static str = "Spreads an image's levels by global histogram equalization.";
    const DOC: &'static str = r#"
Maps every level v through the scaled cumulative histogram, so the output levels are spread
over the full range with a roughly flat histogram: with m the lowest level present and N the
pixel count, lut[m] = 0 and lut[v] = round((cdf(v) − h(m)) · 255 / (N − h(m))) for v > m, in
f32 with ties to even — `cv2.equalizeHist` bit for bit on gray u8. A constant image keeps its
value. u16 uses 65536 levels and 65535 (an extension; OpenCV takes u8 only); f32 is rejected.

Colour images: mode "luma" (default) equalizes the luma Y = (4899·R + 9617·G + 1868·B + 2¹³)
>> 14 (OpenCV's BT.601 `RGB2YCrCb`) and adds the luma change lut[Y] − Y (exact Y) to R, G and
B, which keeps Cb and Cr unchanged (equivalent to equalizing Y of YCbCr and converting back,
without rounding Cb and Cr); "per_channel" equalizes each colour channel on its own. Alpha is
copied.

Reference: OpenCV `cv::equalizeHist`; Gonzalez & Woods, "Digital Image Processing", §3.3.

Example:
    "flat": (op: "filter.equalize", inputs: { "image": "gray.image" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to equalize: u8 or u16, gray, RGB or RGBA.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Equalized image, the input's size and pixel format.",
        )]
    }

    fn new(params: EqualizeParams) -> Result<Self, String> {
        Ok(Equalize { mode: params.mode })
    }
}

impl Operator for Equalize {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = equalize(image, self.mode).map_err(|e| OpError::input("image", e))?;
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// OpenCV's `equalizeHist` table for a histogram of `levels` bins (f32 arithmetic).
fn equalize_table(hist: &[u64], total: u64) -> Vec<u32> {
    let n = hist.len();
    let mut lut = vec![0u32; n];
    let Some(first) = hist.iter().position(|&h| h > 0) else {
        return lut;
    };
    if hist[first] == total {
        lut.fill(first as u32);
        return lut;
    }
    let top = (n - 1) as f32;
    let scale = top / (total - hist[first]) as f32;
    let mut sum = 0u64;
    for (l, &h) in lut.iter_mut().zip(hist).skip(first + 1) {
        sum += h;
        *l = (sum as f32 * scale).round_ties_even().clamp(0.0, top) as u32;
    }
    lut
}

/// Histogram equalization of a u8 or u16 image (see [`Equalize`]'s doc). Errors for f32.
pub fn equalize(image: &Image, mode: ColorMode) -> Result<Image, String> {
    let c = image.channels().count();
    let colour = image.channels() != Channels::Gray;
    let data = match image.data() {
        PixelData::U8(src) => {
            if colour && mode == ColorMode::Luma {
                PixelData::U8(map_luma_u8(src, c, |y| {
                    let table = equalize_table(&histogram_u8(y), y.len() as u64);
                    table.iter().map(|&v| v as u8).collect()
                }))
            } else {
                PixelData::U8(per_channel(src, c, colour, |plane| {
                    let table = equalize_table(&histogram_u8(plane), plane.len() as u64);
                    plane.iter().map(|&v| table[v as usize] as u8).collect()
                }))
            }
        }
        PixelData::U16(src) => {
            if colour && mode == ColorMode::Luma {
                return Err("luma equalization takes u8 colour images; use mode per_channel for u16".into());
            }
            PixelData::U16(per_channel(src, c, colour, |plane| {
                let table = equalize_table(&histogram_u16(plane), plane.len() as u64);
                plane.iter().map(|&v| table[v as usize] as u16).collect()
            }))
        }
        PixelData::F32(_) => {
            return Err("equalization needs a u8 or u16 image, got f32".into());
        }
    };
    Image::new(image.width(), image.height(), image.channels(), data).map_err(|e| e.to_string())
}

/// Applies `f` to every colour channel plane (alpha, the 4th of 4, is copied).
fn per_channel<T: Copy + Default + Send + Sync>(
    src: &[T],
    c: usize,
    colour: bool,
    f: impl Fn(&[T]) -> Vec<T> + Sync,
) -> Vec<T> {
    if !colour || c == 1 {
        return f(src);
    }
    let colours = c.min(3);
    let planes: Vec<Vec<T>> = (0..colours)
        .into_par_iter()
        .map(|ch| {
            let plane: Vec<T> = src.iter().skip(ch).step_by(c).copied().collect();
            f(&plane)
        })
        .collect();
    let mut dst = src.to_vec();
    for (ch, plane) in planes.iter().enumerate() {
        for (d, &v) in dst.iter_mut().skip(ch).step_by(c).zip(plane) {
            *d = v;
        }
    }
    dst
}

/// OpenCV's fixed-point BT.601 luma of an RGB u8 pixel (`RGB2YCrCb`, 14 fractional bits).
fn luma_u8(r: u8, g: u8, b: u8) -> u8 {
    ((u32::from(r) * 4899 + u32::from(g) * 9617 + u32::from(b) * 1868 + (1 << 13)) >> 14) as u8
}

/// Replaces the luma of a u8 colour image: `table_of(luma plane)` gives the new level of every
/// luma level, and R, G, B are shifted by `table[Y] − Y_exact` (rounded, saturated).
fn map_luma_u8(src: &[u8], c: usize, table_of: impl Fn(&[u8]) -> Vec<u8>) -> Vec<u8> {
    let luma: Vec<u8> = src
        .chunks_exact(c)
        .map(|p| luma_u8(p[0], p[1], p[2]))
        .collect();
    let table = table_of(&luma);
    shift_by_luma(src, c, &luma, &table)
}

/// R, G, B shifted by `mapped(Y) − Y_exact`, where `mapped` gives the new luma of every pixel
/// from its integer luma `luma[i]` through `table` (or per pixel for CLAHE).
fn shift_by_luma(src: &[u8], c: usize, luma: &[u8], table: &[u8]) -> Vec<u8> {
    let new_luma: Vec<u8> = luma.iter().map(|&y| table[y as usize]).collect();
    shift_to_luma(src, c, &new_luma)
}

/// R, G, B shifted so that the exact luma becomes `new_luma` (per pixel), alpha copied.
fn shift_to_luma(src: &[u8], c: usize, new_luma: &[u8]) -> Vec<u8> {
    let mut dst = src.to_vec();
    dst.par_chunks_mut(c * 4096)
        .zip(new_luma.par_chunks(4096))
        .for_each(|(d, y)| {
            for (p, &ny) in d.chunks_exact_mut(c).zip(y) {
                let exact = (0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]))
                    + 0.114 * f32::from(p[2]);
                let delta = f32::from(ny) - exact;
                for v in &mut p[..3] {
                    *v = (f32::from(*v) + delta).round_ties_even().clamp(0.0, 255.0) as u8;
                }
            }
        });
    dst
}

params! {
    /// Parameters of `filter.clahe`.
    pub struct ClaheParams {
        /// Contrast limit: a tile's histogram bins are clipped at
        /// `max(1, ⌊clip_limit · tile_pixels / bins⌋)` counts (OpenCV's definition, a multiple
        /// of the flat histogram's height); 0 disables clipping (plain tile-wise
        /// equalization). Default 40 (OpenCV's default).
        clip_limit: f64 = 40.0 => [min = 0.0],
        /// Number of tiles `[across, down]`, each 1..=256. Default [8, 8] (OpenCV's default).
        tiles: [u32; 2] = [8, 8],
        /// Colour images: "luma" (default) or "per_channel", as for filter.equalize.
        mode: ColorMode = ColorMode::Luma,
    }
}

/// Contrast-limited adaptive histogram equalization (`filter.clahe`). See [`clahe`].
#[derive(Debug, Clone, PartialEq)]
pub struct Clahe {
    clip_limit: f64,
    tiles: [usize; 2],
    mode: ColorMode,
}

impl Op for Clahe {
    type Params = ClaheParams;
    const ID: &'static str = "filter.clahe";
    const SUMMARY: &'static str =
        "Equalizes contrast locally, tile by tile, with a limit on the amplification.";
    const DOC: &'static str = r#"
Contrast-limited adaptive histogram equalization (Zuiderveld, "Contrast Limited Adaptive
Histogram Equalization", Graphics Gems IV, 1994), with OpenCV's `CLAHE` arithmetic:

- The image is cut into `tiles[0] × tiles[1]` tiles (if the size is not a multiple of the
  grid, it is first extended right and down with reflect-101 by `tiles − size mod tiles`
  pixels, OpenCV's rule, which adds a full extra tile of rows or columns when only the other
  axis needs padding).
- Each tile's histogram is clipped at `max(1, ⌊clip_limit · tile_pixels / bins⌋)`; the clipped
  count is spread evenly over all bins, the remainder one count every `bins / remainder` bins
  from bin 0. The tile's table is `round(cdf(v) · (bins − 1) / tile_pixels)` in f32.
- Each pixel blends the tables of the four nearest tile centres bilinearly (f32, clamped at
  the image's edges) and rounds half to even.

Gray u8 matches `cv2.createCLAHE(clip_limit, tiles).apply` (256 bins). u16 uses OpenCV's 4096
bins of `v >> 4` and outputs `table << 4`. Colour u8 images are processed through their luma
(mode "luma", as filter.equalize) or per channel; f32 is rejected.

Reference: OpenCV `cv::createCLAHE`, `cv::CLAHE::apply`.

Example:
    "local": (op: "filter.clahe", inputs: { "image": "gray.image" }, params: (clip_limit: 2.0, tiles: (8, 8))),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to equalize: u8 gray/RGB/RGBA or u16 gray/RGB/RGBA.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Equalized image, the input's size and pixel format.",
        )]
    }

    fn new(params: ClaheParams) -> Result<Self, String> {
        let ClaheParams {
            clip_limit,
            tiles,
            mode,
        } = params;
        if !(clip_limit.is_finite() && clip_limit >= 0.0) {
            return Err(format!(
                "`clip_limit` must be finite and ≥ 0, got {clip_limit}"
            ));
        }
        for (axis, t) in ["across", "down"].iter().zip(tiles) {
            if !(1..=MAX_TILES).contains(&t) {
                return Err(format!(
                    "`tiles` {axis} must be between 1 and {MAX_TILES}, got {t}"
                ));
            }
        }
        Ok(Clahe {
            clip_limit,
            tiles: [tiles[0] as usize, tiles[1] as usize],
            mode,
        })
    }
}

impl Operator for Clahe {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = clahe(image, self.clip_limit, self.tiles, self.mode)
            .map_err(|e| OpError::input("image", e))?;
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// CLAHE of a u8 or u16 image with `tiles = [across, down]` (see [`Clahe`]'s doc). Errors for
/// f32 and for u16 colour images in luma mode.
pub fn clahe(
    image: &Image,
    clip_limit: f64,
    tiles: [usize; 2],
    mode: ColorMode,
) -> Result<Image, String> {
    let (w, h) = (image.width(), image.height());
    let c = image.channels().count();
    let colour = image.channels() != Channels::Gray;
    let tiles = [tiles[0].max(1), tiles[1].max(1)];
    let data = match image.data() {
        _ if image.is_empty() => return Ok(image.clone()),
        PixelData::U8(src) => {
            if colour && mode == ColorMode::Luma {
                let luma: Vec<u8> = src
                    .chunks_exact(c)
                    .map(|p| luma_u8(p[0], p[1], p[2]))
                    .collect();
                let new_luma = clahe_plane::<u8>(&luma, w, h, tiles, clip_limit);
                PixelData::U8(shift_to_luma(src, c, &new_luma))
            } else {
                PixelData::U8(per_channel(src, c, colour, |plane| {
                    clahe_plane::<u8>(plane, w, h, tiles, clip_limit)
                }))
            }
        }
        PixelData::U16(src) => {
            if colour && mode == ColorMode::Luma {
                return Err(
                    "luma CLAHE takes u8 colour images; use mode per_channel for u16".into(),
                );
            }
            PixelData::U16(per_channel(src, c, colour, |plane| {
                clahe_plane::<u16>(plane, w, h, tiles, clip_limit)
            }))
        }
        PixelData::F32(_) => return Err("CLAHE needs a u8 or u16 image, got f32".into()),
    };
    Image::new(w, h, image.channels(), data).map_err(|e| e.to_string())
}

/// Sample types CLAHE handles: `BINS` bins of `v >> SHIFT`.
trait ClaheSample: Copy + Default + Send + Sync {
    const BINS: usize;
    fn bin(self) -> usize;
    /// `round_half_even(x)` saturated, shifted back by `SHIFT`.
    fn from_f32(x: f32) -> Self;
}

impl ClaheSample for u8 {
    const BINS: usize = 256;
    fn bin(self) -> usize {
        self as usize
    }
    fn from_f32(x: f32) -> Self {
        x.round_ties_even().clamp(0.0, 255.0) as u8
    }
}

impl ClaheSample for u16 {
    const BINS: usize = 4096;
    fn bin(self) -> usize {
        (self >> 4) as usize
    }
    fn from_f32(x: f32) -> Self {
        (x.round_ties_even().clamp(0.0, 65535.0) as u16) << 4
    }
}

/// CLAHE of one `w × h` plane (non-empty).
fn clahe_plane<T: ClaheSample>(
    src: &[T],
    w: usize,
    h: usize,
    tiles: [usize; 2],
    clip_limit: f64,
) -> Vec<T> {
    let [tx, ty] = tiles;
    let bins = T::BINS;
    // OpenCV extends the image only when some axis is not a multiple of the grid, and then
    // both axes by `tiles − size mod tiles`.
    let (ext_w, ext_h) = if w.is_multiple_of(tx) && h.is_multiple_of(ty) {
        (w, h)
    } else {
        (w + tx - w % tx, h + ty - h % ty)
    };
    let (tile_w, tile_h) = (ext_w / tx, ext_h / ty);
    let columns: Vec<usize> = (0..ext_w)
        .map(|x| map_index(x as isize, w, BorderMode::Reflect101).unwrap_or(0))
        .collect();
    let tile_total = tile_w * tile_h;
    let lut_scale = (bins - 1) as f32 / tile_total as f32;
    let clip = if clip_limit > 0.0 {
        ((clip_limit * tile_total as f64 / bins as f64) as u64).max(1)
    } else {
        0
    };
    // One table of `bins` f32 levels per tile, row-major over the grid.
    let luts: Vec<Vec<f32>> = (0..tx * ty)
        .into_par_iter()
        .map(|k| {
            let (gx, gy) = (k % tx, k / tx);
            let mut hist = vec![0u64; bins];
            let cols = &columns[gx * tile_w..(gx + 1) * tile_w];
            for y in gy * tile_h..(gy + 1) * tile_h {
                let sy = map_index(y as isize, h, BorderMode::Reflect101).unwrap_or(0);
                let row = &src[sy * w..(sy + 1) * w];
                if cols.iter().enumerate().all(|(i, &c)| c == cols[0] + i) {
                    for &v in &row[cols[0]..cols[0] + cols.len()] {
                        hist[v.bin()] += 1;
                    }
                } else {
                    for &c in cols {
                        hist[row[c].bin()] += 1;
                    }
                }
            }
            if clip > 0 {
                clip_histogram(&mut hist, clip);
            }
            let mut sum = 0u64;
            hist.iter()
                .map(|&n| {
                    sum += n;
                    (sum as f32 * lut_scale)
                        .round_ties_even()
                        .clamp(0.0, (bins - 1) as f32)
                })
                .collect()
        })
        .collect();
    // Horizontal interpolation tables, as OpenCV.
    let inv_tw = 1.0f32 / tile_w as f32;
    let mut x_tiles = Vec::with_capacity(w);
    for x in 0..w {
        let txf = x as f32 * inv_tw - 0.5;
        let t1 = txf.floor();
        let xa = txf - t1;
        let t1 = t1 as i64;
        let (i1, i2) = (t1.max(0) as usize, ((t1 + 1) as usize).min(tx - 1));
        x_tiles.push((i1, i2, xa, 1.0 - xa));
    }
    let inv_th = 1.0f32 / tile_h as f32;
    let mut dst = vec![T::default(); w * h];
    dst.par_chunks_mut(BAND_ROWS * w)
        .enumerate()
        .for_each(|(band, out)| {
            for (r, out_row) in out.chunks_exact_mut(w).enumerate() {
                let y = band * BAND_ROWS + r;
                let tyf = y as f32 * inv_th - 0.5;
                let t1 = tyf.floor();
                let ya = tyf - t1;
                let ya1 = 1.0 - ya;
                let t1 = t1 as i64;
                let (j1, j2) = (t1.max(0) as usize, ((t1 + 1) as usize).min(ty - 1));
                let (top, bottom) = (&luts[j1 * tx..(j1 + 1) * tx], &luts[j2 * tx..(j2 + 1) * tx]);
                let row = &src[y * w..(y + 1) * w];
                for ((o, &v), &(i1, i2, xa, xa1)) in out_row.iter_mut().zip(row).zip(&x_tiles) {
                    let b = v.bin();
                    let res = (top[i1][b] * xa1 + top[i2][b] * xa) * ya1
                        + (bottom[i1][b] * xa1 + bottom[i2][b] * xa) * ya;
                    *o = T::from_f32(res);
                }
            }
        });
    dst
}

/// Clips every bin at `clip` and redistributes the excess as OpenCV: evenly over all bins, then
/// the remainder one count every `max(bins / remainder, 1)` bins from bin 0.
fn clip_histogram(hist: &mut [u64], clip: u64) {
    let bins = hist.len() as u64;
    let mut clipped = 0u64;
    for n in hist.iter_mut() {
        if *n > clip {
            clipped += *n - clip;
            *n = clip;
        }
    }
    let batch = clipped / bins;
    let mut residual = clipped - batch * bins;
    for n in hist.iter_mut() {
        *n += batch;
    }
    if residual > 0 {
        let step = (bins / residual).max(1) as usize;
        for n in hist.iter_mut().step_by(step) {
            if residual == 0 {
                break;
            }
            *n += 1;
            residual -= 1;
        }
    }
}
