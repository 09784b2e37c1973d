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
without rounding Cb and Cr: compared with OpenCV's round trip `cvtColor(RGB2YCrCb)`,
`equalizeHist` on Y, `cvtColor(YCrCb2RGB)` on a 1080p image, samples differ by at most 2 levels,
909 of 6.2 million by 2); "per_channel" equalizes each colour channel on its own. Alpha is
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
                    let mut lut = [0u8; 256];
                    for (l, &t) in lut.iter_mut().zip(&table) {
                        *l = t as u8;
                    }
                    apply_lut_u8(plane, &lut)
                }))
            }
        }
        PixelData::U16(src) => {
            if colour && mode == ColorMode::Luma {
                return Err(
                    "luma equalization takes u8 colour images; use mode per_channel for u16".into(),
                );
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

/// `lut[v]` for every sample, in parallel chunks.
fn apply_lut_u8(src: &[u8], lut: &[u8; 256]) -> Vec<u8> {
    let mut dst = ocellus_engine::buffer::zeroed::<u8>(src.len());
    dst.par_chunks_mut(1 << 16)
        .zip(src.par_chunks(1 << 16))
        .for_each(|(d, s)| {
            for (d, &v) in d.iter_mut().zip(s) {
                *d = lut[v as usize];
            }
        });
    dst
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
                let exact =
                    (0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1])) + 0.114 * f32::from(p[2]);
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

Gray u8 matches `cv2.createCLAHE(clip_limit, tiles).apply` bit for bit (256 bins); u16 uses
65536 bins, as OpenCV. Colour u8 images are processed through their luma (mode "luma", as
filter.equalize) or per channel (u16 colour: per channel only); f32 is rejected. One
difference: OpenCV computes the clip count in a C int, which overflows for huge limits on big
tiles (e.g. clip_limit 10⁶ on a 1080p image with 1 tile, where OpenCV then clips at 1); here
it does not overflow.

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

/// Rounds to nearest, ties to even, for |x| < 2²² (adding and subtracting 1.5·2²³); unlike
/// `round_ties_even` it compiles to two additions without SSE4.1. CLAHE results lie in
/// 0..=65535.
fn round_small(x: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0;
    (x + MAGIC) - MAGIC
}

/// Sample types CLAHE handles: one bin per level.
trait ClaheSample: Copy + Default + Send + Sync {
    const BINS: usize;
    fn bin(self) -> usize;
    /// `round_half_even(x)` saturated.
    fn from_f32(x: f32) -> Self;
}

impl ClaheSample for u8 {
    const BINS: usize = 256;
    fn bin(self) -> usize {
        self as usize
    }
    fn from_f32(x: f32) -> Self {
        round_small(x).clamp(0.0, 255.0) as u8
    }
}

impl ClaheSample for u16 {
    const BINS: usize = 65536;
    fn bin(self) -> usize {
        self as usize
    }
    fn from_f32(x: f32) -> Self {
        round_small(x).clamp(0.0, 65535.0) as u16
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
    let mut dst = ocellus_engine::buffer::zeroed::<T>(w * h);
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
    if let Some(step) = bins.checked_div(residual) {
        for n in hist.iter_mut().step_by(step.max(1) as usize) {
            if residual == 0 {
                break;
            }
            *n += 1;
            residual -= 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::random_u8;
    use crate::filter::threshold::tests::smooth;
    use proptest::prelude::*;

    fn gray(w: usize, h: usize, data: Vec<u8>) -> Image {
        Image::from_u8(w, h, Channels::Gray, data).unwrap()
    }

    /// cv2.equalizeHist(smooth(12, 10, 8)).
    const EQUALIZED: [u8; 120] = [
        19, 30, 43, 47, 26, 69, 159, 114, 94, 159, 201, 231, 13, 9, 58, 64, 30, 41, 159, 131, 195,
        144, 186, 204, 60, 17, 15, 39, 120, 133, 131, 88, 126, 236, 214, 221, 4, 56, 21, 79, 148,
        99, 73, 144, 161, 165, 242, 246, 11, 24, 34, 107, 77, 107, 120, 103, 165, 174, 227, 229, 9,
        73, 114, 99, 56, 186, 174, 214, 191, 240, 249, 253, 56, 36, 103, 148, 126, 144, 214, 216,
        208, 195, 189, 251, 62, 90, 47, 144, 126, 186, 174, 199, 178, 208, 255, 32, 69, 116, 88,
        88, 77, 159, 227, 199, 236, 238, 246, 2, 114, 92, 144, 176, 88, 150, 186, 167, 221, 223, 0,
        56,
    ];

    /// cv2.createCLAHE(2.0, (4, 3)).apply(smooth(16, 12, 9)).
    const CLAHE_16X12: [u8; 192] = [
        112, 128, 80, 175, 80, 68, 175, 211, 88, 207, 175, 132, 239, 183, 112, 143, 96, 48, 143,
        163, 168, 84, 143, 127, 128, 183, 239, 143, 215, 227, 48, 32, 32, 175, 80, 215, 152, 203,
        80, 223, 112, 148, 159, 132, 223, 100, 48, 64, 92, 52, 211, 124, 177, 121, 199, 186, 144,
        103, 187, 209, 175, 73, 64, 80, 80, 80, 64, 207, 167, 106, 239, 199, 223, 149, 215, 239,
        251, 46, 104, 175, 148, 96, 64, 144, 74, 141, 183, 228, 104, 93, 132, 166, 96, 159, 76,
        175, 64, 96, 207, 143, 168, 112, 239, 135, 207, 207, 143, 191, 24, 80, 143, 159, 96, 135,
        147, 151, 181, 135, 179, 106, 209, 132, 219, 46, 82, 36, 215, 175, 144, 191, 175, 72, 156,
        159, 88, 227, 108, 237, 144, 94, 56, 68, 239, 207, 120, 52, 235, 83, 122, 215, 72, 231,
        197, 151, 40, 47, 86, 175, 251, 128, 32, 80, 207, 195, 199, 183, 175, 159, 136, 231, 96,
        68, 80, 96, 207, 223, 96, 143, 255, 155, 88, 136, 207, 243, 191, 219, 32, 68, 128, 159,
        128, 159,
    ];

    /// cv2.createCLAHE(3.0, (3, 2)).apply(smooth(17, 13, 10)): both axes need padding.
    const CLAHE_17X13: [u8; 221] = [
        12, 85, 36, 121, 141, 156, 134, 131, 159, 67, 99, 146, 142, 219, 11, 36, 49, 97, 24, 61,
        128, 105, 166, 148, 160, 95, 103, 94, 121, 197, 202, 89, 115, 79, 42, 73, 49, 115, 126,
        105, 140, 99, 74, 61, 158, 178, 167, 24, 79, 128, 55, 18, 30, 128, 140, 121, 121, 146, 99,
        169, 152, 126, 164, 173, 63, 110, 140, 85, 46, 105, 86, 182, 151, 111, 175, 149, 69, 134,
        178, 196, 193, 18, 96, 130, 94, 66, 41, 90, 164, 139, 185, 179, 85, 142, 148, 181, 203, 42,
        14, 55, 143, 165, 44, 47, 126, 166, 153, 97, 124, 115, 111, 119, 211, 214, 46, 42, 91, 131,
        145, 76, 48, 70, 197, 157, 155, 122, 156, 163, 203, 152, 48, 41, 91, 71, 110, 82, 48, 78,
        109, 199, 166, 109, 137, 191, 191, 121, 210, 39, 82, 28, 39, 152, 112, 120, 99, 184, 143,
        193, 127, 185, 165, 160, 177, 18, 13, 78, 67, 133, 136, 140, 70, 127, 59, 115, 119, 189,
        160, 189, 173, 211, 35, 24, 82, 70, 101, 170, 88, 36, 152, 128, 109, 90, 105, 146, 192,
        203, 206, 37, 55, 52, 109, 115, 146, 152, 73, 146, 97, 194, 160, 132, 140, 176, 177, 12,
        77, 39, 70, 99, 104, 140, 164,
    ];

    #[test]
    fn equalize_by_hand_and_opencv() {
        // Histogram [2, 1, 1]: scale 255 / (4 − 2) = 127.5, lut = [0, 128 (127.5 to even), 255].
        let out = equalize(&gray(4, 1, vec![0, 0, 1, 2]), ColorMode::Luma).unwrap();
        assert_eq!(out.as_u8().unwrap(), &[0, 0, 128, 255]);
        let out = equalize(&smooth(12, 10, 8), ColorMode::Luma).unwrap();
        assert_eq!(out.as_u8().unwrap(), &EQUALIZED[..]);
        // A constant image keeps its value (as OpenCV).
        let flat = gray(3, 2, vec![9; 6]);
        assert_eq!(equalize(&flat, ColorMode::Luma).unwrap(), flat);
        let wide = Image::from_u16(4, 1, Channels::Gray, vec![0, 0, 1000, 65535]).unwrap();
        let out = equalize(&wide, ColorMode::Luma).unwrap();
        assert_eq!(out.as_u16().unwrap(), &[0, 0, 32768, 65535]);
    }

    #[test]
    fn equalized_histogram_is_flat() {
        let image = smooth(200, 150, 3);
        let src = image.as_u8().unwrap();
        let out = equalize(&image, ColorMode::Luma).unwrap();
        let dst = out.as_u8().unwrap();
        let n = src.len() as f64;
        let hist = histogram_u8(src);
        let first = hist.iter().position(|&h| h > 0).unwrap();
        let lut: Vec<u8> = (0..256)
            .map(|v| dst[src.iter().position(|&s| s as usize == v).unwrap_or(0)])
            .collect();
        let mut cdf = 0u64;
        for v in 0..256 {
            cdf += hist[v];
            if hist[v] == 0 {
                continue;
            }
            // The output cdf at lut[v] is the input cdf at v: a uniform distribution.
            let expected = (cdf - hist[first]) as f64 / (n - hist[first] as f64);
            assert!((f64::from(lut[v]) / 255.0 - expected).abs() <= 0.5 / 255.0 + 1e-6);
        }
        // Monotone: the order of samples is kept.
        for (a, b) in src.iter().zip(dst).zip(src.iter().zip(dst).skip(1)) {
            if a.0 < b.0 {
                assert!(a.1 <= b.1);
            }
        }
    }

    #[test]
    fn colour_equalization() {
        // Gray pixels stay gray and follow the gray equalization in luma mode.
        let plane = random_u8(40, 30, Channels::Gray, 2);
        let rgb: Vec<u8> = plane
            .as_u8()
            .unwrap()
            .iter()
            .flat_map(|&v| [v, v, v])
            .collect();
        let rgb = Image::from_u8(40, 30, Channels::Rgb, rgb).unwrap();
        let expected = equalize(&plane, ColorMode::Luma).unwrap();
        let expected = expected.as_u8().unwrap();
        for mode in [ColorMode::Luma, ColorMode::PerChannel] {
            let out = equalize(&rgb, mode).unwrap();
            for (p, &e) in out.as_u8().unwrap().chunks_exact(3).zip(expected) {
                assert_eq!(p, [e, e, e], "{mode:?}");
            }
        }
        // Per channel: each channel is its own equalization; alpha is copied.
        let rgba = random_u8(16, 9, Channels::Rgba, 5);
        let out = equalize(&rgba, ColorMode::PerChannel).unwrap();
        let src = rgba.as_u8().unwrap();
        for ch in 0..4 {
            let plane: Vec<u8> = src.iter().skip(ch).step_by(4).copied().collect();
            let got: Vec<u8> = out
                .as_u8()
                .unwrap()
                .iter()
                .skip(ch)
                .step_by(4)
                .copied()
                .collect();
            let want = if ch == 3 {
                plane.clone()
            } else {
                equalize(&gray(16, 9, plane), ColorMode::Luma)
                    .unwrap()
                    .as_u8()
                    .unwrap()
                    .to_vec()
            };
            assert_eq!(got, want, "channel {ch}");
        }
        let f = Image::from_f32(1, 1, Channels::Gray, vec![0.5]).unwrap();
        assert!(equalize(&f, ColorMode::Luma).is_err());
        assert!(clahe(&f, 2.0, [2, 2], ColorMode::Luma).is_err());
    }

    #[test]
    fn clahe_matches_opencv() {
        let out = clahe(&smooth(16, 12, 9), 2.0, [4, 3], ColorMode::Luma).unwrap();
        assert_eq!(out.as_u8().unwrap(), &CLAHE_16X12[..]);
        let out = clahe(&smooth(17, 13, 10), 3.0, [3, 2], ColorMode::Luma).unwrap();
        assert_eq!(out.as_u8().unwrap(), &CLAHE_17X13[..]);
    }

    #[test]
    fn clahe_with_one_tile_and_no_limit_is_equalization() {
        let image = random_u8(256, 256, Channels::Gray, 8);
        let a = clahe(&image, 1e9, [1, 1], ColorMode::Luma).unwrap();
        let b = equalize(&image, ColorMode::Luma).unwrap();
        let pairs: Vec<(u8, u8)> = image
            .as_u8()
            .unwrap()
            .iter()
            .copied()
            .zip(a.as_u8().unwrap().iter().copied())
            .collect();
        for (x, y) in a.as_u8().unwrap().iter().zip(b.as_u8().unwrap()) {
            assert!(x.abs_diff(*y) <= 1, "{x} vs {y}");
        }
        // One table everywhere: the output is a monotone function of the input.
        let mut sorted = pairs.clone();
        sorted.sort();
        for w in sorted.windows(2) {
            assert!(w[0].1 <= w[1].1);
        }
        // Clip 0 means no limit.
        let c = clahe(&image, 0.0, [1, 1], ColorMode::Luma).unwrap();
        assert_eq!(a, c);
    }

    #[test]
    fn clahe_extremes() {
        for (w, h) in [(0, 0), (3, 0), (1, 1), (2, 3), (5, 1)] {
            let image = Image::from_u8(w, h, Channels::Gray, vec![100; w * h]).unwrap();
            let out = clahe(&image, 40.0, [8, 8], ColorMode::Luma).unwrap();
            assert_eq!((out.width(), out.height()), (w, h));
            // Every tile sees the same constant: one output value.
            if let Some(&first) = out.as_u8().unwrap().first() {
                assert!(out.as_u8().unwrap().iter().all(|&v| v == first));
            }
        }
        let wide =
            Image::from_u16(20, 10, Channels::Gray, (0..200).map(|v| v * 300).collect()).unwrap();
        let out = clahe(&wide, 2.0, [2, 2], ColorMode::Luma).unwrap();
        // cv2.createCLAHE(2, (2, 2)).apply(arange(200).reshape(10, 20) * 300) as u16.
        let expected: [u16; 200] = [
            1311, 2621, 3932, 5243, 6554, 7864, 8258, 8389, 8257, 7864, 7209, 6815, 6684, 6816,
            7209, 7864, 9175, 10486, 11796, 13107, 14418, 15728, 17039, 18350, 19660, 20971, 21364,
            21496, 21364, 20971, 20316, 19922, 19792, 19923, 20315, 20971, 22282, 23593, 24903,
            26214, 27525, 28835, 30146, 31457, 32767, 34078, 34472, 34603, 34471, 34078, 33423,
            33029, 32898, 33030, 33422, 34078, 35389, 36700, 38010, 39321, 36569, 37748, 38928,
            40108, 41287, 42466, 42821, 42939, 42820, 42467, 41877, 41523, 41405, 41523, 41876,
            42466, 43646, 44826, 46005, 47185, 37617, 38534, 39452, 40370, 41287, 42204, 42480,
            42572, 42480, 42205, 41746, 41470, 41379, 41471, 41745, 42204, 43122, 44040, 44957,
            45874, 33423, 34078, 34734, 35389, 36044, 36700, 36896, 36962, 36896, 36700, 36372,
            36175, 36110, 36175, 36372, 36700, 37355, 38010, 38666, 39321, 29753, 30670, 31588,
            32505, 33422, 34340, 34616, 34708, 34615, 34340, 33882, 33606, 33515, 33606, 33881,
            34340, 35258, 36176, 37093, 38010, 31326, 32505, 33685, 34865, 36044, 37224, 37578,
            37696, 37578, 37224, 36634, 36280, 36162, 36280, 36634, 37224, 38404, 39584, 40762,
            41942, 40632, 41942, 43253, 44564, 45874, 47185, 47578, 47710, 47578, 47185, 46530,
            46136, 46006, 46137, 46529, 47185, 48496, 49807, 51117, 52428, 53739, 55049, 56360,
            57671, 58981, 60292, 60686, 60817, 60685, 60292, 59637, 59243, 59112, 59244, 59636,
            60292, 61603, 62914, 64224, 65535,
        ];
        assert_eq!(out.as_u16().unwrap(), &expected[..]);
    }

    #[test]
    fn identical_for_any_thread_count() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let image = random_u8(333, 250, Channels::Rgb, 4);
        let run = || {
            (
                clahe(&image, 2.0, [8, 8], ColorMode::Luma).unwrap(),
                clahe(&image, 3.0, [5, 3], ColorMode::PerChannel).unwrap(),
                equalize(&image, ColorMode::Luma).unwrap(),
            )
        };
        assert_eq!(pool(1).install(run), pool(3).install(run));
    }

    #[test]
    fn new_checks_params() {
        let c = |clip_limit: f64, tiles: [u32; 2]| {
            Clahe::new(ClaheParams {
                clip_limit,
                tiles,
                ..ClaheParams::default()
            })
        };
        assert!(c(40.0, [8, 8]).is_ok());
        assert!(c(-1.0, [8, 8]).is_err());
        assert!(c(f64::NAN, [8, 8]).is_err());
        assert!(c(2.0, [0, 8]).is_err());
        assert!(c(2.0, [8, 300]).is_err());
    }

    proptest! {
        #[test]
        fn equalize_is_monotone(data in proptest::collection::vec(any::<u8>(), 1..300)) {
            let n = data.len();
            let out = equalize(&gray(n, 1, data.clone()), ColorMode::Luma).unwrap();
            let out = out.as_u8().unwrap();
            for i in 0..n {
                for j in 0..n {
                    if data[i] < data[j] {
                        prop_assert!(out[i] <= out[j]);
                    }
                }
            }
            prop_assert_eq!(*out.iter().max().unwrap(), if data.iter().all(|&v| v == data[0]) { data[0] } else { 255 });
        }
    }
}
