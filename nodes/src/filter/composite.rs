//! `filter.over` (Porter–Duff alpha compositing) and `filter.radiometric` (dark-frame and
//! flat-field correction): per-pixel operators on two or three images.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Depth, Image, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

/// Background rows per parallel task of `filter.over`.
const ROWS_PER_TASK: usize = 16;

/// Samples per parallel task of `filter.radiometric`: a multiple of 1, 3 and 4, so tasks start
/// on pixel boundaries and sample `k` of a task is channel `k mod c`.
const SAMPLES_PER_TASK: usize = 3 * 4 * 1024;

params! {
    /// Parameters of `filter.over`.
    pub struct OverParams {
        /// Position of the foreground's top-left pixel in the background, [x, y] in px; may be
        /// negative or beyond the background (the foreground is clipped). Default [0, 0].
        offset: [i64; 2] = [0, 0],
    }
}

/// Porter–Duff "over" (`filter.over`). See [`over`].
#[derive(Debug, Clone, PartialEq)]
pub struct Over {
    offset: [i64; 2],
}

impl Op for Over {
    type Params = OverParams;
    const ID: &'static str = "filter.over";
    const SUMMARY: &'static str =
        "Composites an RGBA foreground over a background with Porter–Duff \"over\".";
    const DOC: &'static str = r#"
Porter–Duff "over" with straight (not premultiplied) alpha. With αf, αb the alphas scaled to
0..1 (an RGB background has αb = 1):

    αo = αf + αb·(1 − αf)
    Co = (Cf·αf + Cb·αb·(1 − αf)) / αo      (Co = 0 where αo = 0)

For an RGB background this is Co = Cf·αf + Cb·(1 − αf). The output has the background's
size, channels and sample type; the foreground (RGBA, same sample type) is placed with its
top-left pixel at `offset` and clipped, and background pixels it does not cover are copied.

Numerics: u8 and u16 are exact rational arithmetic in integers, rounded once to nearest
(with M = 255 or 65535: Co = round((Cf·af + Cb·(M − af)) / M) for RGB backgrounds; for RGBA,
αo·M² = af·M + ab·(M − af), Ao = round(αo·M), Co = round((Cf·af·M + Cb·ab·(M − af)) / (αo·M²))).
f32 uses the formulas in f32 with alphas clamped to [0, 1].

Reference: T. Porter, T. Duff, "Compositing digital images", SIGGRAPH 1984.

Example:
    "logo_on_card": (op: "filter.over", inputs: { "foreground": "logo.image", "background": "card.image" }, params: (offset: [40, -10])),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "foreground",
                PortType::Image,
                "RGBA image with straight alpha, same sample type as the background.",
            ),
            PortSpec::new(
                "background",
                PortType::Image,
                "RGB or RGBA image (straight alpha).",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The composite, in the background's size and format.",
        )]
    }

    fn new(params: OverParams) -> Result<Self, String> {
        Ok(Over {
            offset: params.offset,
        })
    }
}

impl Operator for Over {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let fg = inputs.image("foreground")?;
        let bg = inputs.image("background")?;
        if fg.channels() != Channels::Rgba {
            return Err(OpError::input(
                "foreground",
                format!("must be RGBA, got {}", fg.format()),
            ));
        }
        if bg.channels() == Channels::Gray {
            return Err(OpError::input(
                "background",
                format!("must be RGB or RGBA, got {}", bg.format()),
            ));
        }
        if fg.depth() != bg.depth() {
            return Err(OpError::input(
                "foreground",
                format!(
                    "has {} samples but the background has {} (convert with filter.convert_type)",
                    fg.depth().name(),
                    bg.depth().name()
                ),
            ));
        }
        let out = over(fg, bg, self.offset).map_err(OpError::failed)?;
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// Samples with an integer or float "over".
trait OverSample: Copy + Send + Sync {
    /// Foreground RGBA over an opaque RGB pixel.
    fn over_opaque(f: &[Self], b: &mut [Self]);
    /// Foreground RGBA over an RGBA pixel.
    fn over_alpha(f: &[Self], b: &mut [Self]);
}

/// Integer "over" with full scale `M`.
macro_rules! integer_over {
    ($t:ty, $m:expr) => {
        impl OverSample for $t {
            #[inline]
            fn over_opaque(f: &[Self], b: &mut [Self]) {
                const M: u64 = $m;
                let af = u64::from(f[3]);
                for k in 0..3 {
                    let x = u64::from(f[k]) * af + u64::from(b[k]) * (M - af);
                    b[k] = ((x + M / 2) / M) as $t;
                }
            }

            #[inline]
            fn over_alpha(f: &[Self], b: &mut [Self]) {
                const M: u64 = $m;
                let (af, ab) = (u64::from(f[3]), u64::from(b[3]));
                let wf = af * M;
                let wb = ab * (M - af);
                let den = wf + wb;
                if den == 0 {
                    b[..4].fill(0 as $t);
                    return;
                }
                for k in 0..3 {
                    let num = u64::from(f[k]) * wf + u64::from(b[k]) * wb;
                    b[k] = ((2 * num + den) / (2 * den)) as $t;
                }
                b[3] = ((den + M / 2) / M) as $t;
            }
        }
    };
}

integer_over!(u8, 255);
integer_over!(u16, 65535);

impl OverSample for f32 {
    #[inline]
    fn over_opaque(f: &[Self], b: &mut [Self]) {
        let af = f[3].clamp(0.0, 1.0);
        for k in 0..3 {
            b[k] = f[k] * af + b[k] * (1.0 - af);
        }
    }

    #[inline]
    fn over_alpha(f: &[Self], b: &mut [Self]) {
        let af = f[3].clamp(0.0, 1.0);
        let wb = b[3].clamp(0.0, 1.0) * (1.0 - af);
        let ao = af + wb;
        if ao <= 0.0 {
            b[..4].fill(0.0);
            return;
        }
        for k in 0..3 {
            b[k] = (f[k] * af + b[k] * wb) / ao;
        }
        b[3] = ao;
    }
}

/// Composites RGBA `fg` over RGB/RGBA `bg` (same sample type) with `fg`'s top-left pixel at
/// `offset` = [x, y] in `bg`. Errors for other formats.
pub fn over(fg: &Image, bg: &Image, offset: [i64; 2]) -> Result<Image, String> {
    if fg.channels() != Channels::Rgba || bg.channels() == Channels::Gray {
        return Err(format!(
            "over needs an RGBA foreground and an RGB or RGBA background, got {} and {}",
            fg.format(),
            bg.format()
        ));
    }
    let geometry = Placement::new(fg, bg, offset);
    let data = match (fg.data(), bg.data()) {
        (PixelData::U8(f), PixelData::U8(b)) => PixelData::U8(composite(f, b, bg, &geometry)),
        (PixelData::U16(f), PixelData::U16(b)) => PixelData::U16(composite(f, b, bg, &geometry)),
        (PixelData::F32(f), PixelData::F32(b)) => PixelData::F32(composite(f, b, bg, &geometry)),
        _ => {
            return Err(format!(
                "foreground and background sample types differ ({} and {})",
                fg.depth().name(),
                bg.depth().name()
            ));
        }
    };
    Image::new(bg.width(), bg.height(), bg.channels(), data).map_err(|e| e.to_string())
}

/// Where the foreground lands: background columns `x0..x1` read foreground column
/// `x − ox`, background rows `y0..y1` read foreground row `y − oy`.
struct Placement {
    fg_width: usize,
    ox: i64,
    oy: i64,
    x0: usize,
    x1: usize,
    y0: usize,
    y1: usize,
}

impl Placement {
    fn new(fg: &Image, bg: &Image, [ox, oy]: [i64; 2]) -> Placement {
        // Image sizes fit in i64 (their sample counts fit in usize and are checked).
        let span = |o: i64, f: usize, b: usize| {
            let start = o.clamp(0, b as i64);
            let end = o.saturating_add(f as i64).clamp(start, b as i64);
            (start as usize, end as usize)
        };
        let (x0, x1) = span(ox, fg.width(), bg.width());
        let (y0, y1) = span(oy, fg.height(), bg.height());
        Placement {
            fg_width: fg.width(),
            ox,
            oy,
            x0,
            x1,
            y0,
            y1,
        }
    }
}

fn composite<T: OverSample>(f: &[T], b: &[T], bg: &Image, g: &Placement) -> Vec<T> {
    let mut out = b.to_vec();
    let cb = bg.channels().count();
    let row = bg.width() * cb;
    if row == 0 || g.x0 >= g.x1 {
        return out;
    }
    let fx0 = (g.x0 as i64 - g.ox) as usize;
    let cols = g.x1 - g.x0;
    out.par_chunks_mut(ROWS_PER_TASK * row)
        .enumerate()
        .for_each(|(band, rows)| {
            for (i, line) in rows.chunks_exact_mut(row).enumerate() {
                let y = band * ROWS_PER_TASK + i;
                if y < g.y0 || y >= g.y1 {
                    continue;
                }
                let fy = (y as i64 - g.oy) as usize;
                let start = (fy * g.fg_width + fx0) * 4;
                let Some(fline) = f.get(start..start + cols * 4) else {
                    continue;
                };
                let bline = &mut line[g.x0 * cb..g.x1 * cb];
                if cb == 4 {
                    for (fp, bp) in fline.chunks_exact(4).zip(bline.chunks_exact_mut(4)) {
                        T::over_alpha(fp, bp);
                    }
                } else {
                    for (fp, bp) in fline.chunks_exact(4).zip(bline.chunks_exact_mut(3)) {
                        T::over_opaque(fp, bp);
                    }
                }
            }
        });
    out
}

// ---------------------------------------------------------------------------------------------
// Radiometric correction

param_enum! {
    /// Sample type of the corrected image.
    pub enum OutputDepth {
        /// The input image's sample type (integers rounded and saturated).
        Same = "same",
        /// 8-bit unsigned, rounded and saturated.
        U8 = "u8",
        /// 16-bit unsigned, rounded and saturated.
        U16 = "u16",
        /// 32-bit float, not clipped.
        F32 = "f32",
    }
}

params! {
    /// Parameters of `filter.radiometric`.
    pub struct RadiometricParams {
        /// Output sample type: "same" (the image's; default), "u8", "u16" or "f32".
        depth: OutputDepth = OutputDepth::Same,
    }
}

/// Dark-frame and gain (flat-field) correction (`filter.radiometric`). See [`radiometric`].
#[derive(Debug, Clone, PartialEq)]
pub struct Radiometric {
    depth: OutputDepth,
}

impl Op for Radiometric {
    type Params = RadiometricParams;
    const ID: &'static str = "filter.radiometric";
    const SUMMARY: &'static str =
        "Radiometric correction (I − B)·W / mean(W): dark-frame subtraction and gain map.";
    const DOC: &'static str = r#"
Corrects an image for a sensor's dark signal and its pixel-to-pixel gain (flat-field
correction): out = (I − B) · W / mean(W), sample by sample, with I the image, B the dark frame
(bias/dark current, in the image's units) and W the gain map (for a measured flat field F,
W = 1/(F − B)). Dividing by mean(W) keeps the overall level: a uniform gain map changes
nothing.

mean(W) is taken per channel, over all pixels of that channel of W (so each colour channel
keeps its own level, and white balance is not changed). It is summed in f64 over fixed blocks
added in a fixed order, so the result does not depend on the thread count. A mean that is 0
or not finite is an error naming the channel.

The three images must have the same size and channels; their sample types may differ (each
sample is taken at its numeric value: a u8 image with an f32 gain map is fine). Arithmetic is
f64. Output: the image's sample type by default, or `depth`; integers are rounded to nearest
(ties to even) and saturated, f32 is not clipped. Empty images give an empty result.

Reference: flat-field correction, e.g. S. B. Howell, Handbook of CCD Astronomy, 2nd ed.,
Cambridge University Press 2006, §4.5.

Example:
    "flat": (op: "filter.radiometric", inputs: { "image": "raw.image", "dark": "dark.image", "gain": "gain.image" }, params: (depth: "f32")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("image", PortType::Image, "Image to correct (I)."),
            PortSpec::new(
                "dark",
                PortType::Image,
                "Dark frame (B), same size and channels, in the image's units.",
            ),
            PortSpec::new(
                "gain",
                PortType::Image,
                "Gain map (W), same size and channels.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Corrected image, same size and channels.",
        )]
    }

    fn new(params: RadiometricParams) -> Result<Self, String> {
        Ok(Radiometric {
            depth: params.depth,
        })
    }
}

impl Operator for Radiometric {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let dark = inputs.image("dark")?;
        let gain = inputs.image("gain")?;
        for (port, other) in [("dark", dark), ("gain", gain)] {
            if (other.width(), other.height(), other.channels())
                != (image.width(), image.height(), image.channels())
            {
                return Err(OpError::input(
                    port,
                    format!(
                        "is {}×{} {}, the image is {}×{} {}",
                        other.width(),
                        other.height(),
                        other.channels().name(),
                        image.width(),
                        image.height(),
                        image.channels().name()
                    ),
                ));
            }
        }
        let depth = match self.depth {
            OutputDepth::Same => image.depth(),
            OutputDepth::U8 => Depth::U8,
            OutputDepth::U16 => Depth::U16,
            OutputDepth::F32 => Depth::F32,
        };
        let out = radiometric(image, dark, gain, depth).map_err(|e| OpError::input("gain", e))?;
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// Samples `range` of `data` as f64, into `out`.
fn load(data: &PixelData, start: usize, out: &mut [f64]) {
    let end = start + out.len();
    match data {
        PixelData::U8(v) => {
            for (o, &x) in out.iter_mut().zip(&v[start..end]) {
                *o = f64::from(x);
            }
        }
        PixelData::U16(v) => {
            for (o, &x) in out.iter_mut().zip(&v[start..end]) {
                *o = f64::from(x);
            }
        }
        PixelData::F32(v) => {
            for (o, &x) in out.iter_mut().zip(&v[start..end]) {
                *o = f64::from(x);
            }
        }
    }
}

/// Per-channel means of `image`'s samples, in f64, summed over fixed blocks in order.
pub fn channel_means(image: &Image) -> Vec<f64> {
    let c = image.channels().count();
    let n = image.data().len();
    let partials: Vec<[f64; 4]> = (0..n.div_ceil(SAMPLES_PER_TASK))
        .into_par_iter()
        .map(|block| {
            let start = block * SAMPLES_PER_TASK;
            let mut buf = vec![0.0; SAMPLES_PER_TASK.min(n - start)];
            load(image.data(), start, &mut buf);
            let mut sums = [0.0; 4];
            for px in buf.chunks_exact(c) {
                for (s, &x) in sums.iter_mut().zip(px) {
                    *s += x;
                }
            }
            sums
        })
        .collect();
    let pixels = (n / c.max(1)) as f64;
    (0..c)
        .map(|k| partials.iter().map(|p| p[k]).sum::<f64>() / pixels)
        .collect()
}

/// Converts f64 results to a sample type (round half to even and saturate for integers).
trait Store: Copy + Default + Send + Sync {
    fn store(x: f64) -> Self;
}

impl Store for u8 {
    fn store(x: f64) -> Self {
        x.round_ties_even() as u8
    }
}

impl Store for u16 {
    fn store(x: f64) -> Self {
        x.round_ties_even() as u16
    }
}

impl Store for f32 {
    fn store(x: f64) -> Self {
        x as f32
    }
}

fn correct<O: Store>(image: &Image, dark: &Image, gain: &Image, factors: &[f64]) -> Vec<O> {
    let mut out = ocellus_engine::buffer::zeroed::<O>(image.data().len());
    out.par_chunks_mut(SAMPLES_PER_TASK)
        .enumerate()
        .for_each(|(block, dst)| {
            let start = block * SAMPLES_PER_TASK;
            let mut i = vec![0.0; dst.len()];
            let mut b = vec![0.0; dst.len()];
            let mut w = vec![0.0; dst.len()];
            load(image.data(), start, &mut i);
            load(dark.data(), start, &mut b);
            load(gain.data(), start, &mut w);
            for ((((o, i), b), w), k) in dst
                .iter_mut()
                .zip(&i)
                .zip(&b)
                .zip(&w)
                .zip(factors.iter().cycle())
            {
                *o = O::store((i - b) * w * k);
            }
        });
    out
}

/// `(image − dark) · gain / mean(gain)` per sample, mean per channel, into `depth`. The three
/// images must share size and channels (checked); errors when a channel's mean is 0 or not
/// finite.
pub fn radiometric(
    image: &Image,
    dark: &Image,
    gain: &Image,
    depth: Depth,
) -> Result<Image, String> {
    for other in [dark, gain] {
        if (other.width(), other.height(), other.channels())
            != (image.width(), image.height(), image.channels())
        {
            return Err("the image, dark frame and gain map differ in size or channels".into());
        }
    }
    let (w, h, channels) = (image.width(), image.height(), image.channels());
    if image.data().is_empty() {
        return Image::zeros(w, h, ocellus_engine::value::PixelFormat { channels, depth })
            .map_err(|e| e.to_string());
    }
    let means = channel_means(gain);
    let mut factors = Vec::with_capacity(means.len());
    for (k, m) in means.iter().enumerate() {
        if *m == 0.0 || !m.is_finite() {
            return Err(format!(
                "the gain map's mean over channel {k} is {m}; it must be finite and non-zero"
            ));
        }
        factors.push(1.0 / m);
    }
    let data = match depth {
        Depth::U8 => PixelData::U8(correct(image, dark, gain, &factors)),
        Depth::U16 => PixelData::U16(correct(image, dark, gain, &factors)),
        Depth::F32 => PixelData::F32(correct(image, dark, gain, &factors)),
    };
    Image::new(w, h, channels, data).map_err(|e| e.to_string())
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

    fn rgba(w: usize, h: usize, px: [u8; 4]) -> Image {
        Image::from_u8(w, h, Channels::Rgba, px.repeat(w * h)).unwrap()
    }

    #[test]
    fn over_opaque_background_by_hand() {
        // (200·128 + 100·127)/255 = 38300/255 = 150.2 → 150; (0·128 + 50·127)/255 = 24.9 → 25.
        let fg = rgba(1, 1, [200, 0, 255, 128]);
        let bg = Image::from_u8(1, 1, Channels::Rgb, vec![100, 50, 0]).unwrap();
        let out = over(&fg, &bg, [0, 0]).unwrap();
        assert_eq!(out.as_u8().unwrap(), [150, 25, 128]);
        // Fully opaque and fully transparent foregrounds.
        let out = over(&rgba(1, 1, [1, 2, 3, 255]), &bg, [0, 0]).unwrap();
        assert_eq!(out.as_u8().unwrap(), [1, 2, 3]);
        let out = over(&rgba(1, 1, [1, 2, 3, 0]), &bg, [0, 0]).unwrap();
        assert_eq!(out, bg);
    }

    #[test]
    fn over_transparent_background_by_hand() {
        // αf = 0.5 (128), αb = 0.5 (128): wf = 128·255 = 32640, wb = 128·127 = 16256,
        // den = 48896; Ao = round(48896/255) = round(191.75) = 192;
        // C = (200·32640 + 100·16256)/48896 = 8153600/48896 = 166.75 → 167.
        let fg = rgba(1, 1, [200, 200, 200, 128]);
        let bg = rgba(1, 1, [100, 100, 100, 128]);
        let out = over(&fg, &bg, [0, 0]).unwrap();
        assert_eq!(out.as_u8().unwrap(), [167, 167, 167, 192]);
        // Both transparent: all zero.
        let out = over(&rgba(1, 1, [9, 9, 9, 0]), &rgba(1, 1, [5, 5, 5, 0]), [0, 0]).unwrap();
        assert_eq!(out.as_u8().unwrap(), [0, 0, 0, 0]);
        // A transparent foreground leaves an RGBA background unchanged.
        let bg = rgba(1, 1, [10, 20, 30, 40]);
        assert_eq!(over(&rgba(1, 1, [9, 9, 9, 0]), &bg, [0, 0]).unwrap(), bg);
    }

    #[test]
    fn over_offsets_clip() {
        let bg = Image::from_u8(4, 3, Channels::Rgb, vec![0; 36]).unwrap();
        let fg = rgba(2, 2, [255, 255, 255, 255]);
        let white = |out: &Image| -> Vec<(usize, usize)> {
            let v = out.as_u8().unwrap();
            (0..12)
                .filter(|&p| v[p * 3] == 255)
                .map(|p| (p % 4, p / 4))
                .collect()
        };
        assert_eq!(white(&over(&fg, &bg, [3, 2]).unwrap()), [(3, 2)].to_vec());
        assert_eq!(white(&over(&fg, &bg, [-1, -1]).unwrap()), [(0, 0)].to_vec());
        assert_eq!(
            white(&over(&fg, &bg, [1, 0]).unwrap()),
            [(1, 0), (2, 0), (1, 1), (2, 1)].to_vec()
        );
        for offset in [[4, 0], [0, 3], [-2, 0], [i64::MIN, i64::MAX], [i64::MAX, 0]] {
            assert_eq!(over(&fg, &bg, offset).unwrap(), bg, "{offset:?}");
        }
        let empty = Image::from_u8(0, 0, Channels::Rgb, vec![]).unwrap();
        assert_eq!(over(&fg, &empty, [0, 0]).unwrap(), empty);
    }

    #[test]
    fn over_u16_and_f32() {
        let fg = Image::from_u16(1, 1, Channels::Rgba, vec![65535, 0, 1000, 32768]).unwrap();
        let bg = Image::from_u16(1, 1, Channels::Rgb, vec![0, 65535, 1000]).unwrap();
        let out = over(&fg, &bg, [0, 0]).unwrap();
        // 65535·32768/65535 = 32768; 65535·32767/65535 = 32767; 1000.
        assert_eq!(out.as_u16().unwrap(), [32768, 32767, 1000]);
        let fg = Image::from_f32(1, 1, Channels::Rgba, vec![1.0, 0.0, 0.5, 0.25]).unwrap();
        let bg = Image::from_f32(1, 1, Channels::Rgba, vec![0.0, 1.0, 0.5, 0.5]).unwrap();
        let out = over(&fg, &bg, [0, 0]).unwrap();
        // αo = 0.25 + 0.5·0.75 = 0.625; R = 0.25/0.625 = 0.4; G = 0.375/0.625 = 0.6.
        let v = out.as_f32().unwrap();
        for (g, e) in v.iter().zip([0.4, 0.6, 0.5, 0.625]) {
            assert!((g - e).abs() < 1e-6, "{v:?}");
        }
    }

    #[test]
    fn over_operator_checks_formats() {
        let specs = Over::inputs();
        let op = Over::new(OverParams::default()).unwrap();
        let rgb = Value::image(Image::from_u8(1, 1, Channels::Rgb, vec![0; 3]).unwrap());
        let values = [Some(rgb.clone()), Some(rgb.clone())];
        let err = op.run(&ctx(), &Inputs::new(&specs, &values)).unwrap_err();
        assert!(err.to_string().contains("must be RGBA"), "{err}");
        let fg16 = Value::image(Image::from_u16(1, 1, Channels::Rgba, vec![0; 4]).unwrap());
        let values = [Some(fg16), Some(rgb.clone())];
        let err = op.run(&ctx(), &Inputs::new(&specs, &values)).unwrap_err();
        assert!(err.to_string().contains("u16"), "{err}");
        let fg = Value::image(rgba(1, 1, [255, 0, 0, 255]));
        let gray = Value::image(Image::from_u8(1, 1, Channels::Gray, vec![0]).unwrap());
        let values = [Some(fg.clone()), Some(gray)];
        assert!(op.run(&ctx(), &Inputs::new(&specs, &values)).is_err());
        let values = [Some(fg), Some(rgb)];
        let mut out = op.run(&ctx(), &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Image(img)) = out.take("image") else {
            panic!("expected an image");
        };
        assert_eq!(img.as_u8().unwrap(), [255, 0, 0]);
    }

    /// The formulas in f64 for one u8 pixel.
    fn over_reference(f: [u8; 4], b: [u8; 4], opaque: bool) -> Vec<f64> {
        let af = f64::from(f[3]) / 255.0;
        let ab = if opaque { 1.0 } else { f64::from(b[3]) / 255.0 };
        let ao = af + ab * (1.0 - af);
        let mut out: Vec<f64> = (0..3)
            .map(|k| {
                if ao == 0.0 {
                    0.0
                } else {
                    (f64::from(f[k]) * af + f64::from(b[k]) * ab * (1.0 - af)) / ao
                }
            })
            .collect();
        if !opaque {
            out.push(ao * 255.0);
        }
        out
    }

    proptest! {
        #[test]
        fn over_u8_is_the_rounded_formula(f: [u8; 4], b: [u8; 4], opaque: bool) {
            let fg = Image::from_u8(1, 1, Channels::Rgba, f.to_vec()).unwrap();
            let bg = if opaque {
                Image::from_u8(1, 1, Channels::Rgb, b[..3].to_vec()).unwrap()
            } else {
                Image::from_u8(1, 1, Channels::Rgba, b.to_vec()).unwrap()
            };
            let out = over(&fg, &bg, [0, 0]).unwrap();
            for (g, e) in out.as_u8().unwrap().iter().zip(over_reference(f, b, opaque)) {
                prop_assert!((f64::from(*g) - e).abs() <= 0.5 + 1e-9, "{} vs {}", g, e);
            }
        }

        #[test]
        fn opaque_background_stays_opaque_and_alpha_never_drops(f: [u8; 4], b: [u8; 4]) {
            let fg = Image::from_u8(1, 1, Channels::Rgba, f.to_vec()).unwrap();
            let bg = Image::from_u8(1, 1, Channels::Rgba, b.to_vec()).unwrap();
            let a = over(&fg, &bg, [0, 0]).unwrap().as_u8().unwrap()[3];
            prop_assert!(a >= f[3].max(b[3]));
            let bg = Image::from_u8(1, 1, Channels::Rgba, [b[0], b[1], b[2], 255].to_vec()).unwrap();
            prop_assert_eq!(over(&fg, &bg, [0, 0]).unwrap().as_u8().unwrap()[3], 255);
        }
    }

    #[test]
    fn radiometric_by_hand() {
        // W = [1, 3] → mean 2; (10 − 2)·1/2 = 4; (20 − 4)·3/2 = 24.
        let image = Image::from_u8(2, 1, Channels::Gray, vec![10, 20]).unwrap();
        let dark = Image::from_u8(2, 1, Channels::Gray, vec![2, 4]).unwrap();
        let gain = Image::from_f32(2, 1, Channels::Gray, vec![1.0, 3.0]).unwrap();
        let out = radiometric(&image, &dark, &gain, Depth::U8).unwrap();
        assert_eq!(out.as_u8().unwrap(), [4, 24]);
        // Below zero saturates for u8, not for f32; 2.5 rounds to 2 (ties to even).
        let dark = Image::from_u8(2, 1, Channels::Gray, vec![20, 4]).unwrap();
        let out = radiometric(&image, &dark, &gain, Depth::F32).unwrap();
        assert_eq!(out.as_f32().unwrap(), [-5.0, 24.0]);
        let out = radiometric(&image, &dark, &gain, Depth::U8).unwrap();
        assert_eq!(out.as_u8().unwrap(), [0, 24]);
        let image = Image::from_u8(2, 1, Channels::Gray, vec![5, 0]).unwrap();
        let zero = Image::from_u8(2, 1, Channels::Gray, vec![0, 0]).unwrap();
        let gain = Image::from_u8(2, 1, Channels::Gray, vec![1, 3]).unwrap();
        let out = radiometric(&image, &zero, &gain, Depth::U16).unwrap();
        assert_eq!(out.as_u16().unwrap(), [2, 0]);
    }

    #[test]
    fn radiometric_means_are_per_channel() {
        // Channel 0 gain [2, 2] (mean 2), channel 1 gain [1, 3] (mean 2), channel 2 [4, 0].
        let image = Image::from_f32(2, 1, Channels::Rgb, vec![1.0; 6]).unwrap();
        let dark = Image::from_f32(2, 1, Channels::Rgb, vec![0.0; 6]).unwrap();
        let gain =
            Image::from_f32(2, 1, Channels::Rgb, vec![2.0, 1.0, 4.0, 2.0, 3.0, 0.0]).unwrap();
        assert_eq!(channel_means(&gain), [2.0, 2.0, 2.0]);
        let out = radiometric(&image, &dark, &gain, Depth::F32).unwrap();
        assert_eq!(out.as_f32().unwrap(), [1.0, 0.5, 2.0, 1.0, 1.5, 0.0]);
    }

    #[test]
    fn radiometric_errors() {
        let image = Image::from_u8(2, 1, Channels::Gray, vec![1, 2]).unwrap();
        let zero = Image::from_u8(2, 1, Channels::Gray, vec![0, 0]).unwrap();
        let err = radiometric(&image, &zero, &zero, Depth::U8).unwrap_err();
        assert!(err.contains("channel 0"), "{err}");
        let nan = Image::from_f32(2, 1, Channels::Gray, vec![f32::NAN, 1.0]).unwrap();
        assert!(radiometric(&image, &zero, &nan, Depth::U8).is_err());
        let cancel = Image::from_f32(2, 1, Channels::Gray, vec![-1.0, 1.0]).unwrap();
        assert!(radiometric(&image, &zero, &cancel, Depth::U8).is_err());
        let op = Radiometric::new(RadiometricParams::default()).unwrap();
        let specs = Radiometric::inputs();
        let small = Value::image(Image::from_u8(1, 1, Channels::Gray, vec![1]).unwrap());
        let values = [
            Some(Value::image(image.clone())),
            Some(small),
            Some(Value::image(image.clone())),
        ];
        let err = op.run(&ctx(), &Inputs::new(&specs, &values)).unwrap_err();
        assert!(err.to_string().contains("input `dark`: is 1×1"), "{err}");
        let values = [
            Some(Value::image(image.clone())),
            Some(Value::image(zero.clone())),
            Some(Value::image(zero)),
        ];
        let err = op.run(&ctx(), &Inputs::new(&specs, &values)).unwrap_err();
        assert!(err.to_string().contains("input `gain`"), "{err}");
        let empty = Image::from_u8(0, 3, Channels::Rgb, vec![]).unwrap();
        let out = radiometric(&empty, &empty, &empty, Depth::F32).unwrap();
        assert_eq!((out.width(), out.height(), out.depth()), (0, 3, Depth::F32));
    }

    #[test]
    fn radiometric_is_thread_count_independent_and_unit_gain_is_subtraction() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let (w, h) = (301, 97);
        let image = random_u8(w, h, Channels::Rgb, 1);
        let dark = random_u8(w, h, Channels::Rgb, 2);
        let data: Vec<f32> = randoms(3, w * h * 3)
            .iter()
            .map(|&r| 0.5 + r as f32)
            .collect();
        let gain = Image::from_f32(w, h, Channels::Rgb, data).unwrap();
        let run = || radiometric(&image, &dark, &gain, Depth::F32).unwrap();
        assert_eq!(pool(1).install(run), pool(4).install(run));
        let ones = Image::from_f32(w, h, Channels::Rgb, vec![7.0; w * h * 3]).unwrap();
        let out = radiometric(&image, &dark, &ones, Depth::F32).unwrap();
        for ((o, i), d) in out
            .as_f32()
            .unwrap()
            .iter()
            .zip(image.as_u8().unwrap())
            .zip(dark.as_u8().unwrap())
        {
            assert_eq!(*o, f32::from(*i) - f32::from(*d));
        }
    }

    proptest! {
        #[test]
        fn radiometric_scaling_the_gain_changes_nothing(seed: u64, k in 0.1f64..100.0) {
            let (w, h) = (7, 5);
            let image = random_u8(w, h, Channels::Rgba, seed);
            let dark = random_u8(w, h, Channels::Rgba, seed ^ 1);
            let r = randoms(seed ^ 2, w * h * 4);
            let gain = Image::from_f32(w, h, Channels::Rgba, r.iter().map(|&x| (0.5 + x) as f32).collect()).unwrap();
            let scaled = Image::from_f32(w, h, Channels::Rgba, r.iter().map(|&x| ((0.5 + x) * k) as f32).collect()).unwrap();
            let a = radiometric(&image, &dark, &gain, Depth::F32).unwrap();
            let b = radiometric(&image, &dark, &scaled, Depth::F32).unwrap();
            for (x, y) in a.as_f32().unwrap().iter().zip(b.as_f32().unwrap()) {
                prop_assert!((x - y).abs() <= 1e-4 * (1.0 + x.abs()), "{} vs {}", x, y);
            }
        }
    }
}
