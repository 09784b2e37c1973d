//! `filter.in_range` and `filter.chroma_key`: masks selecting pixels by colour.
//!
//! [`in_range`] is OpenCV's `inRange` (every channel inside inclusive bounds), in RGB or in
//! OpenCV's HSV convention, with hue intervals that may wrap around red. [`chroma_key`] pulls a
//! soft matte from the distance to a key colour in the CbCr chroma plane.
//!
//! Both run per pixel over fixed-size chunks in parallel (`par_chunks_mut`); results are
//! identical for any thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Depth, Image, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::color::{Conversion, convert_color};

/// Pixels per parallel chunk.
const CHUNK_PIXELS: usize = 1 << 14;

param_enum! {
    /// Colour space in which `filter.in_range` compares.
    pub enum RangeSpace {
        /// The image's own channels.
        Rgb = "rgb",
        /// OpenCV's HSV: u8 H 0..180 (degrees / 2), S and V 0..255; f32 H 0..360, S and V 0..1.
        Hsv = "hsv",
    }
}

params! {
    /// Parameters of `filter.in_range`.
    pub struct InRangeParams {
        /// Inclusive lower bounds, one per compared channel (gray 1; rgb 3, or 4 to test alpha
        /// too on RGBA; hsv 3 = H, S, V, or 4 with alpha) or a single value for all channels,
        /// in the image's units (integer images: rounded to nearest). Default [0].
        lower: Vec<f64> = vec![0.0],
        /// Inclusive upper bounds, same count and units as `lower`. Default [255].
        upper: Vec<f64> = vec![255.0],
        /// "rgb" (default) compares the image's channels; "hsv" converts RGB first. In hsv, a
        /// hue lower bound above the upper bound selects the wrapped interval
        /// `H ≥ lower or H ≤ upper` (e.g. reds: [170, 10]).
        space: RangeSpace = RangeSpace::Rgb,
    }
}

/// Colour-range mask (`filter.in_range`). See [`in_range`].
#[derive(Debug, Clone, PartialEq)]
pub struct InRange {
    lower: Vec<f64>,
    upper: Vec<f64>,
    space: RangeSpace,
}

impl Op for InRange {
    type Params = InRangeParams;
    const ID: &'static str = "filter.in_range";
    const SUMMARY: &'static str =
        "Marks the pixels whose every channel lies between lower and upper bounds.";
    const DOC: &'static str = r#"
Outputs a gray u8 mask: 255 where `lower[k] ≤ v[k] ≤ upper[k]` for every compared channel k,
else 0 (OpenCV's `inRange`; integer images compare with the bounds rounded to nearest, as
OpenCV converts scalar bounds to the image's depth).

Space "hsv" converts RGB(A) pixels to OpenCV's HSV first: for u8 with the fixed-point tables
of `cvtColor(COLOR_RGB2HSV)` (H = hue/2 in 0..180, S and V in 0..255, bit-exact); for f32
with OpenCV's float formula (H in degrees 0..360, S and V 0..1); u16 is rejected in hsv. The
hue is the only circular channel: with `lower[0] > upper[0]` the hue test becomes
`H ≥ lower[0] or H ≤ upper[0]` (OpenCV itself would select nothing; use two ranges there).

Reference: OpenCV `cv::inRange`, `cv::cvtColor` (`COLOR_RGB2HSV`).

Example:
    "green": (op: "filter.in_range", inputs: { "image": "card.image" }, params: (space: hsv, lower: [35, 50, 50], upper: [85, 255, 255])),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to test, any pixel format (RGB or RGBA for hsv).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "mask",
            PortType::Image,
            "Gray u8 mask, 255 inside the range and 0 outside.",
        )]
    }

    fn new(params: InRangeParams) -> Result<Self, String> {
        let InRangeParams {
            lower,
            upper,
            space,
        } = params;
        if lower.is_empty() || lower.len() > 4 {
            return Err(format!("`lower` needs 1 to 4 values, got {}", lower.len()));
        }
        if upper.len() != lower.len() {
            return Err(format!(
                "`upper` needs as many values as `lower` ({}), got {}",
                lower.len(),
                upper.len()
            ));
        }
        if let Some(v) = lower.iter().chain(&upper).find(|v| v.is_nan()) {
            return Err(format!("bounds must not be NaN, got {v}"));
        }
        Ok(InRange {
            lower,
            upper,
            space,
        })
    }
}

impl Operator for InRange {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let mask = in_range(image, &self.lower, &self.upper, self.space)
            .map_err(|e| OpError::input("image", e))?;
        Ok(Outputs::new().with("mask", Value::image(mask)))
    }
}

/// Per-channel inclusive bounds after broadcasting: `(lo, hi)` for each compared channel.
fn expand_bounds(lower: &[f64], upper: &[f64], n: usize) -> Result<Vec<(f64, f64)>, String> {
    match lower.len() {
        1 => Ok(vec![(lower[0], upper[0]); n]),
        k if k == n => Ok(lower.iter().copied().zip(upper.iter().copied()).collect()),
        k => Err(format!(
            "{k} bounds given for {n} compared channels (give 1 or {n})"
        )),
    }
}

/// Inclusive test with an optionally wrapped first (hue) interval.
#[inline]
fn inside<T: PartialOrd + Copy>(v: &[T], bounds: &[(T, T)], wrap_first: bool) -> bool {
    v.iter()
        .zip(bounds)
        .enumerate()
        .all(|(k, (&x, &(lo, hi)))| {
            if k == 0 && wrap_first {
                x >= lo || x <= hi
            } else {
                x >= lo && x <= hi
            }
        })
}

/// Integer bound: rounded to nearest and clamped to `[-1, max + 1]` so an out-of-range bound
/// still compares correctly.
fn int_bound(v: f64, max: f64) -> i32 {
    v.round_ties_even().clamp(-1.0, max + 1.0) as i32
}

/// A gray u8 mask of the pixels of `image` inside `[lower, upper]` (see [`InRange`]'s doc).
pub fn in_range(
    image: &Image,
    lower: &[f64],
    upper: &[f64],
    space: RangeSpace,
) -> Result<Image, String> {
    let c = image.channels().count();
    let (w, h) = (image.width(), image.height());
    if lower.is_empty() || lower.len() != upper.len() {
        return Err("`lower` and `upper` need the same number (1 to 4) of values".into());
    }
    let hsv = space == RangeSpace::Hsv;
    if hsv && image.channels() == Channels::Gray {
        return Err("hsv needs an RGB or RGBA image, got gray".into());
    }
    // Three bounds on RGBA leave alpha out.
    let n = if lower.len() == 3 && c == 4 { 3 } else { c };
    let bounds = expand_bounds(lower, upper, n)?;
    let wrap = hsv && bounds[0].0 > bounds[0].1;
    if hsv && image.depth() == Depth::U16 {
        return Err("hsv takes u8 or f32 images, got u16".into());
    }
    // HSV: convert once (OpenCV's tables for u8, its float formula for f32; alpha is kept),
    // then compare like RGB.
    let converted;
    let image = if hsv {
        converted = convert_color(image, Conversion::RgbToHsv)?;
        &converted
    } else {
        image
    };
    let mut mask = vec![0u8; w * h];
    match image.data() {
        PixelData::U8(src) => {
            let b: Vec<(i32, i32)> = bounds
                .iter()
                .map(|&(lo, hi)| (int_bound(lo, 255.0), int_bound(hi, 255.0)))
                .collect();
            fill_mask(&mut mask, src, c, |p| {
                let mut px = [0i32; 4];
                for (d, &s) in px.iter_mut().zip(p) {
                    *d = i32::from(s);
                }
                inside(&px[..n], &b, wrap)
            });
        }
        PixelData::U16(src) => {
            let b: Vec<(i32, i32)> = bounds
                .iter()
                .map(|&(lo, hi)| (int_bound(lo, 65535.0), int_bound(hi, 65535.0)))
                .collect();
            fill_mask(&mut mask, src, c, |p| {
                let mut px = [0i32; 4];
                for (d, &s) in px.iter_mut().zip(p) {
                    *d = i32::from(s);
                }
                inside(&px[..n], &b, false)
            });
        }
        PixelData::F32(src) => {
            let b: Vec<(f32, f32)> = bounds
                .iter()
                .map(|&(lo, hi)| (lo as f32, hi as f32))
                .collect();
            fill_mask(&mut mask, src, c, |p| {
                let mut px = [0f32; 4];
                px[..c].copy_from_slice(p);
                inside(&px[..n], &b, wrap)
            });
        }
    }
    Image::from_u8(w, h, Channels::Gray, mask).map_err(|e| e.to_string())
}

/// `mask[i] = test(pixel i) ? 255 : 0` in parallel chunks.
fn fill_mask<T: Copy + Sync>(
    mask: &mut [u8],
    src: &[T],
    c: usize,
    test: impl Fn(&[T]) -> bool + Sync,
) {
    mask.par_chunks_mut(CHUNK_PIXELS)
        .zip(src.par_chunks(CHUNK_PIXELS * c))
        .for_each(|(m, s)| {
            for (o, p) in m.iter_mut().zip(s.chunks_exact(c)) {
                *o = if test(p) { 255 } else { 0 };
            }
        });
}

params! {
    /// Parameters of `filter.chroma_key`.
    pub struct ChromaKeyParams {
        /// Key (backdrop) colour `[r, g, b]`, each 0..1 whatever the image depth (0..1 of full
        /// scale: 255 for u8, 65535 for u16, 1.0 for f32). Default pure green [0, 1, 0].
        key: [f64; 3] = [0.0, 1.0, 0.0],
        /// Chroma distance (CbCr plane, full-scale units, 0..≈0.8) up to which a pixel is
        /// fully keyed out (alpha 0). Default 0.1.
        tolerance: f64 = 0.1 => [min = 0.0, max = 2.0],
        /// Width of the soft edge beyond `tolerance` over which alpha ramps linearly to 1;
        /// 0 gives a hard matte. Default 0.1.
        softness: f64 = 0.1 => [min = 0.0, max = 2.0],
    }
}

/// Chroma keyer (`filter.chroma_key`). See [`chroma_key`].
#[derive(Debug, Clone, PartialEq)]
pub struct ChromaKey {
    key: [f64; 3],
    tolerance: f64,
    softness: f64,
}

impl Op for ChromaKey {
    type Params = ChromaKeyParams;
    const ID: &'static str = "filter.chroma_key";
    const SUMMARY: &'static str =
        "Pulls a matte that removes a backdrop colour, by distance in the chroma plane.";
    const DOC: &'static str = r#"
Keys out a backdrop colour. Every pixel's chroma (Cb, Cr) of BT.601 YCbCr is computed from its
R, G, B in full-scale units (Cb = −0.168736·R − 0.331264·G + 0.5·B, Cr = 0.5·R − 0.418688·G −
0.081312·B, R, G, B in 0..1), and its distance d to the key colour's chroma gives the matte:
alpha = 0 for d ≤ tolerance, 1 for d ≥ tolerance + softness, linear in between (a hard step
when softness is 0). Measuring in the CbCr plane ignores luma, so brighter or darker
(greyer) patches of the backdrop, and lighting that adds white, key alike; this is the
approach of the common video keyers (e.g. FFmpeg's `chromakey` filter, whose `similarity` and
`blend` are `tolerance` and `softness` here, without its 2×2 chroma averaging).

Outputs `mask`: the matte as a gray image of the input's depth (0 = keyed out, full scale =
kept: 255 for u8, 65535 for u16, 1.0 for f32); and `image`: the input as RGBA with the matte as
alpha (multiplied with the input's alpha if it has one, rounded). Gray images are rejected.

Reference: Jack, "Video Demystified", ch. on chroma keying; FFmpeg `chromakey` filter.

Example:
    "key": (op: "filter.chroma_key", inputs: { "image": "plate.image" }, params: (key: (0.0, 0.8, 0.2), tolerance: 0.12)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "RGB or RGBA image, any depth.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "mask",
                PortType::Image,
                "Gray matte, the input's depth: 0 where keyed out, full scale where kept.",
            ),
            PortSpec::new(
                "image",
                PortType::Image,
                "The input as RGBA with the matte as alpha.",
            ),
        ]
    }

    fn new(params: ChromaKeyParams) -> Result<Self, String> {
        let ChromaKeyParams {
            key,
            tolerance,
            softness,
        } = params;
        if let Some(k) = key.iter().find(|k| !(0.0..=1.0).contains(*k)) {
            return Err(format!("`key` components must be in 0..1, got {k}"));
        }
        if !(tolerance.is_finite() && tolerance >= 0.0) {
            return Err(format!(
                "`tolerance` must be finite and ≥ 0, got {tolerance}"
            ));
        }
        if !(softness.is_finite() && softness >= 0.0) {
            return Err(format!("`softness` must be finite and ≥ 0, got {softness}"));
        }
        Ok(ChromaKey {
            key,
            tolerance,
            softness,
        })
    }
}

impl Operator for ChromaKey {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let (mask, keyed) = chroma_key(image, self.key, self.tolerance, self.softness)
            .map_err(|e| OpError::input("image", e))?;
        Ok(Outputs::new()
            .with("mask", Value::image(mask))
            .with("image", Value::image(keyed)))
    }
}

/// BT.601 chroma (Cb, Cr) of an RGB triple in 0..1.
fn chroma(r: f32, g: f32, b: f32) -> (f32, f32) {
    (
        -0.168_736 * r - 0.331_264 * g + 0.5 * b,
        0.5 * r - 0.418_688 * g - 0.081_312 * b,
    )
}

/// Sample types keyed here: full scale and conversions.
trait KeySample: Copy + Default + Send + Sync {
    fn to_unit(self) -> f32;
    fn from_unit(x: f32) -> Self;
}

impl KeySample for u8 {
    fn to_unit(self) -> f32 {
        f32::from(self) * (1.0 / 255.0)
    }
    fn from_unit(x: f32) -> Self {
        (x * 255.0).round_ties_even().clamp(0.0, 255.0) as u8
    }
}

impl KeySample for u16 {
    fn to_unit(self) -> f32 {
        f32::from(self) * (1.0 / 65535.0)
    }
    fn from_unit(x: f32) -> Self {
        (x * 65535.0).round_ties_even().clamp(0.0, 65535.0) as u16
    }
}

impl KeySample for f32 {
    fn to_unit(self) -> f32 {
        self
    }
    fn from_unit(x: f32) -> Self {
        x
    }
}

/// The chroma-key matte of `image` (RGB or RGBA) and the image as RGBA with it as alpha (see
/// [`ChromaKey`]'s doc): `key` in 0..1, `tolerance` and `softness` in CbCr units.
pub fn chroma_key(
    image: &Image,
    key: [f64; 3],
    tolerance: f64,
    softness: f64,
) -> Result<(Image, Image), String> {
    let c = image.channels().count();
    if image.channels() == Channels::Gray {
        return Err("chroma keying needs an RGB or RGBA image, got gray".into());
    }
    let (w, h) = (image.width(), image.height());
    let (kb, kr) = chroma(key[0] as f32, key[1] as f32, key[2] as f32);
    let (tol, soft) = (tolerance as f32, softness as f32);
    let alpha_of = move |r: f32, g: f32, b: f32| -> f32 {
        let (cb, cr) = chroma(r, g, b);
        let d = ((cb - kb) * (cb - kb) + (cr - kr) * (cr - kr)).sqrt();
        if d <= tol {
            0.0
        } else if soft <= 0.0 || d >= tol + soft {
            1.0
        } else {
            (d - tol) / soft
        }
    };
    let (mask, keyed) = match image.data() {
        PixelData::U8(src) => {
            let (m, k) = key_samples(src, c, alpha_of);
            (PixelData::U8(m), PixelData::U8(k))
        }
        PixelData::U16(src) => {
            let (m, k) = key_samples(src, c, alpha_of);
            (PixelData::U16(m), PixelData::U16(k))
        }
        PixelData::F32(src) => {
            let (m, k) = key_samples(src, c, alpha_of);
            (PixelData::F32(m), PixelData::F32(k))
        }
    };
    let mask = Image::new(w, h, Channels::Gray, mask).map_err(|e| e.to_string())?;
    let keyed = Image::new(w, h, Channels::Rgba, keyed).map_err(|e| e.to_string())?;
    Ok((mask, keyed))
}

/// Matte and RGBA samples of interleaved `c`-channel samples.
fn key_samples<T: KeySample>(
    src: &[T],
    c: usize,
    alpha_of: impl Fn(f32, f32, f32) -> f32 + Sync,
) -> (Vec<T>, Vec<T>) {
    let pixels = src.len() / c;
    let mut mask = vec![T::default(); pixels];
    let mut rgba = vec![T::default(); pixels * 4];
    mask.par_chunks_mut(CHUNK_PIXELS)
        .zip(rgba.par_chunks_mut(CHUNK_PIXELS * 4))
        .zip(src.par_chunks(CHUNK_PIXELS * c))
        .for_each(|((m, o), s)| {
            for ((m, o), p) in m
                .iter_mut()
                .zip(o.chunks_exact_mut(4))
                .zip(s.chunks_exact(c))
            {
                let alpha = alpha_of(p[0].to_unit(), p[1].to_unit(), p[2].to_unit());
                *m = T::from_unit(alpha);
                o[..3].copy_from_slice(&p[..3]);
                let existing = if c == 4 { p[3].to_unit() } else { 1.0 };
                o[3] = T::from_unit(alpha * existing);
            }
        });
    (mask, rgba)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::random_u8;
    use proptest::prelude::*;

    fn rgb(pixels: &[[u8; 3]]) -> Image {
        let data = pixels.iter().flatten().copied().collect();
        Image::from_u8(pixels.len(), 1, Channels::Rgb, data).unwrap()
    }

    #[test]
    fn hsv_matches_opencv() {
        // cv2.cvtColor(px, COLOR_RGB2HSV): in_range tests each pixel's HSV exactly.
        let cases = [
            ([255, 0, 0], [0, 255, 255]),
            ([0, 255, 0], [60, 255, 255]),
            ([0, 0, 255], [120, 255, 255]),
            ([10, 200, 130], [79, 242, 200]),
            ([128, 128, 128], [0, 0, 128]),
            ([255, 0, 1], [0, 255, 255]),
            ([1, 2, 3], [105, 170, 3]),
        ];
        for (p, [h, s, v]) in cases {
            let bounds = [f64::from(h), f64::from(s), f64::from(v)];
            let hit = in_range(&rgb(&[p]), &bounds, &bounds, RangeSpace::Hsv).unwrap();
            assert_eq!(hit.as_u8().unwrap(), &[255], "{p:?}");
            let below = bounds.map(|b| b - 1.0);
            let miss = in_range(&rgb(&[p]), &below, &below, RangeSpace::Hsv).unwrap();
            assert_eq!(miss.as_u8().unwrap(), &[0], "{p:?}");
        }
        let green = Image::from_f32(1, 1, Channels::Rgb, vec![0.0, 1.0, 0.0]).unwrap();
        let hit = in_range(
            &green,
            &[119.999, 0.999, 1.0],
            &[120.001, 1.0, 1.0],
            RangeSpace::Hsv,
        );
        assert_eq!(hit.unwrap().as_u8().unwrap(), &[255]);
    }

    #[test]
    fn rgb_ranges_by_hand() {
        let image = rgb(&[[10, 20, 30], [10, 21, 30], [9, 20, 30], [255, 255, 255]]);
        let mask = in_range(
            &image,
            &[10.0, 0.0, 0.0],
            &[10.0, 20.0, 255.0],
            RangeSpace::Rgb,
        )
        .unwrap();
        assert_eq!(mask.as_u8().unwrap(), &[255, 0, 0, 0]);
        // One bound for all channels; bounds round to nearest (19.6 → 20).
        let mask = in_range(&image, &[9.6], &[30.4], RangeSpace::Rgb).unwrap();
        assert_eq!(mask.as_u8().unwrap(), &[255, 255, 0, 0]);
        let gray = Image::from_u16(3, 1, Channels::Gray, vec![0, 500, 70]).unwrap();
        let mask = in_range(&gray, &[50.0], &[500.0], RangeSpace::Rgb).unwrap();
        assert_eq!(mask.as_u8().unwrap(), &[0, 255, 255]);
        // RGBA: three bounds ignore alpha, four test it.
        let rgba = Image::from_u8(2, 1, Channels::Rgba, vec![5, 5, 5, 0, 5, 5, 5, 200]).unwrap();
        let mask = in_range(&rgba, &[0.0; 3], &[10.0; 3], RangeSpace::Rgb).unwrap();
        assert_eq!(mask.as_u8().unwrap(), &[255, 255]);
        let mask = in_range(
            &rgba,
            &[0.0; 4],
            &[10.0, 10.0, 10.0, 255.0],
            RangeSpace::Rgb,
        )
        .unwrap();
        assert_eq!(mask.as_u8().unwrap(), &[255, 255]);
        let mask = in_range(&rgba, &[0.0; 4], &[10.0; 4], RangeSpace::Rgb).unwrap();
        assert_eq!(mask.as_u8().unwrap(), &[255, 0]);
        let f = Image::from_f32(3, 1, Channels::Gray, vec![0.1, 0.5, f32::NAN]).unwrap();
        let mask = in_range(&f, &[0.2], &[1.0], RangeSpace::Rgb).unwrap();
        assert_eq!(mask.as_u8().unwrap(), &[0, 255, 0]);
    }

    #[test]
    fn hsv_ranges_and_wrap() {
        // Red (H 0), a red-magenta (H ≈ 175), green (H 60).
        let image = rgb(&[[255, 0, 0], [255, 0, 40], [0, 255, 0]]);
        let mask = in_range(
            &image,
            &[170.0, 50.0, 50.0],
            &[10.0, 255.0, 255.0],
            RangeSpace::Hsv,
        )
        .unwrap();
        assert_eq!(mask.as_u8().unwrap(), &[255, 255, 0]);
        let mask = in_range(
            &image,
            &[35.0, 50.0, 50.0],
            &[85.0, 255.0, 255.0],
            RangeSpace::Hsv,
        )
        .unwrap();
        assert_eq!(mask.as_u8().unwrap(), &[0, 0, 255]);
        // Gray and u16 inputs are rejected in hsv; wrong bound counts too.
        let gray = Image::from_u8(1, 1, Channels::Gray, vec![1]).unwrap();
        assert!(in_range(&gray, &[0.0], &[1.0], RangeSpace::Hsv).is_err());
        assert!(in_range(&image, &[0.0, 0.0], &[1.0, 1.0], RangeSpace::Rgb).is_err());
    }

    #[test]
    fn hsv_wrap_is_the_union_of_two_ranges() {
        let image = random_u8(64, 40, Channels::Rgba, 3);
        let wrapped = in_range(
            &image,
            &[160.0, 30.0, 20.0],
            &[20.0, 255.0, 255.0],
            RangeSpace::Hsv,
        )
        .unwrap();
        let high = in_range(
            &image,
            &[160.0, 30.0, 20.0],
            &[255.0, 255.0, 255.0],
            RangeSpace::Hsv,
        )
        .unwrap();
        let low = in_range(
            &image,
            &[0.0, 30.0, 20.0],
            &[20.0, 255.0, 255.0],
            RangeSpace::Hsv,
        )
        .unwrap();
        for ((&w, &h), &l) in wrapped
            .as_u8()
            .unwrap()
            .iter()
            .zip(high.as_u8().unwrap())
            .zip(low.as_u8().unwrap())
        {
            assert_eq!(w, h | l);
        }
    }

    #[test]
    fn chroma_key_by_hand() {
        let image = rgb(&[[0, 204, 0], [0, 102, 0], [255, 0, 255], [40, 244, 40]]);
        let (mask, keyed) = chroma_key(&image, [0.0, 0.8, 0.0], 0.1, 0.0).unwrap();
        // Pure key: 0. Magenta: opposite chroma, kept. The key plus grey (40 added to every
        // channel) has exactly the key's chroma: keyed out.
        let m = mask.as_u8().unwrap();
        assert_eq!(m[0], 0);
        assert_eq!(m[2], 255);
        assert_eq!(m[3], 0);
        // Half-bright green is far in chroma (its chroma is halved): kept with a hard matte.
        assert_eq!(m[1], 255);
        assert_eq!(keyed.channels(), Channels::Rgba);
        let k = keyed.as_u8().unwrap();
        assert_eq!(&k[8..12], &[255, 0, 255, 255]);
        assert_eq!(k[3], 0);
    }

    #[test]
    fn chroma_key_soft_edge_and_formats() {
        // Distances 0, tolerance + softness / 2 and beyond along the Cb axis: blue changes Cb
        // by 0.5 per unit. The key is black (chroma 0).
        let image = Image::from_f32(
            3,
            1,
            Channels::Rgb,
            vec![0.0, 0.0, 0.0, 0.0, 0.0, 0.3, 0.0, 0.0, 1.0],
        )
        .unwrap();
        let (mask, _) = chroma_key(&image, [0.0, 0.0, 0.0], 0.1, 0.1).unwrap();
        let m = mask.as_f32().unwrap();
        // Blue 0.3: Cb 0.15, Cr −0.0244; d = 0.1520 → alpha (0.152 − 0.1)/0.1 = 0.52.
        let d = (0.15f32 * 0.15 + 0.024_393_6 * 0.024_393_6).sqrt();
        assert_eq!(m[0], 0.0);
        assert!((m[1] - (d - 0.1) / 0.1).abs() < 1e-5, "{}", m[1]);
        assert_eq!(m[2], 1.0);
        // RGBA: the matte multiplies the existing alpha; u16 works.
        let rgba = Image::from_u16(1, 1, Channels::Rgba, vec![65535, 0, 65535, 32768]).unwrap();
        let (mask, keyed) = chroma_key(&rgba, [0.0, 1.0, 0.0], 0.1, 0.1).unwrap();
        assert_eq!(mask.as_u16().unwrap(), &[65535]);
        assert_eq!(keyed.as_u16().unwrap(), &[65535, 0, 65535, 32768]);
        let gray = Image::from_u8(1, 1, Channels::Gray, vec![1]).unwrap();
        assert!(chroma_key(&gray, [0.0, 1.0, 0.0], 0.1, 0.1).is_err());
        let empty = Image::from_u8(0, 0, Channels::Rgb, vec![]).unwrap();
        let (mask, keyed) = chroma_key(&empty, [0.0, 1.0, 0.0], 0.1, 0.1).unwrap();
        assert!(mask.is_empty() && keyed.is_empty());
    }

    #[test]
    fn new_checks_params() {
        let r = |lower: Vec<f64>, upper: Vec<f64>| {
            InRange::new(InRangeParams {
                lower,
                upper,
                space: RangeSpace::Rgb,
            })
        };
        assert!(r(vec![0.0], vec![1.0]).is_ok());
        assert!(r(vec![], vec![]).is_err());
        assert!(r(vec![0.0; 5], vec![1.0; 5]).is_err());
        assert!(r(vec![0.0, 1.0], vec![1.0]).is_err());
        assert!(r(vec![f64::NAN], vec![1.0]).is_err());
        let k = |key: [f64; 3], tolerance: f64| {
            ChromaKey::new(ChromaKeyParams {
                key,
                tolerance,
                softness: 0.1,
            })
        };
        assert!(k([0.0, 1.0, 0.0], 0.1).is_ok());
        assert!(k([0.0, 2.0, 0.0], 0.1).is_err());
        assert!(k([0.0, 1.0, 0.0], f64::NAN).is_err());
        assert!(k([0.0, 1.0, 0.0], -0.1).is_err());
    }

    proptest! {
        #[test]
        fn mask_is_binary_and_matches_definition(
            data in proptest::collection::vec(any::<u8>(), 3..90),
            lo in 0u8..=255,
            hi in 0u8..=255,
        ) {
            let n = data.len() / 3;
            let image = Image::from_u8(n, 1, Channels::Rgb, data[..n * 3].to_vec()).unwrap();
            let mask = in_range(&image, &[f64::from(lo)], &[f64::from(hi)], RangeSpace::Rgb).unwrap();
            for (m, p) in mask.as_u8().unwrap().iter().zip(data.chunks_exact(3)) {
                let inside = p.iter().all(|&v| v >= lo && v <= hi);
                prop_assert_eq!(*m, if inside { 255 } else { 0 });
            }
        }

        #[test]
        fn matte_is_monotone_in_tolerance(r in 0u8..=255, g in 0u8..=255, b in 0u8..=255, t in 0.0f64..0.5) {
            let image = rgb(&[[r, g, b]]);
            let (tight, _) = chroma_key(&image, [0.1, 0.9, 0.2], t, 0.05).unwrap();
            let (loose, _) = chroma_key(&image, [0.1, 0.9, 0.2], t + 0.05, 0.05).unwrap();
            prop_assert!(loose.as_u8().unwrap()[0] <= tight.as_u8().unwrap()[0]);
        }
    }
}
