//! `filter.pyr_down`, `filter.pyr_up`, `filter.pyramid`, `filter.pyramid_reconstruct`: Gaussian
//! and Laplacian image pyramids with OpenCV's `pyrDown` / `pyrUp` arithmetic.
//!
//! [`pyr_down`] blurs with the 5×5 kernel `[1 4 6 4 1]ᵀ[1 4 6 4 1] / 256` (reflect-101 border)
//! and keeps the even rows and columns; [`pyr_up`] inserts zero rows and columns and blurs with
//! 4× that kernel (`/ 64`). Integer images sum exactly (u8 in u16, u16 in u32) and round once at the end
//! (`(s + 128) ≫ 8` and `(s + 32) ≫ 6`, as OpenCV), so u8 results are bit-identical to OpenCV's.
//!
//! The Laplacian pyramid stores `Gᵢ − pyr_up(Gᵢ₊₁)` in f32, with `Gᵢ₊₁` and `pyr_up` computed in
//! the input's depth: for integer images each level is an exact integer, and
//! [`reconstruct`] rebuilds the input bit-exactly.
//!
//! How it runs: destination rows are cut into fixed bands processed in parallel
//! (`par_chunks_mut`); each band filters the source rows it needs horizontally into a scratch
//! buffer (rows shared by two bands are computed by both with the same arithmetic), then
//! combines them vertically. Results are bit-identical for any thread count.

use std::ops::{Add, Mul};

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params::NoParams;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::border::{BorderMode, map_index};

/// Destination rows per parallel band.
const BAND_ROWS: usize = 32;

/// Most pyramid levels.
pub const MAX_LEVELS: u32 = 32;

/// One step down the Gaussian pyramid (`filter.pyr_down`). See [`pyr_down`].
#[derive(Debug, Clone, PartialEq)]
pub struct PyrDown;

impl Op for PyrDown {
    type Params = NoParams;
    const ID: &'static str = "filter.pyr_down";
    const SUMMARY: &'static str = "Blurs an image with a 5×5 Gaussian and halves its size.";
    const DOC: &'static str = r#"
One step down a Gaussian pyramid, as OpenCV's `cv::pyrDown`: the image is convolved with the
5×5 kernel [1 4 6 4 1]ᵀ[1 4 6 4 1] / 256 (reflect-101 border) and the even rows and columns are
kept. The output is ⌈w/2⌉ × ⌈h/2⌉ in the input's pixel format.

Numerics: u8 and u16 sum exactly in integers and round once, `(s + 128) ≫ 8`, so u8 output is
bit-identical to OpenCV's; f32 sums in f32.

Reference: OpenCV `cv::pyrDown`; P. Burt and E. Adelson, "The Laplacian pyramid as a compact
image code", IEEE Trans. Communications 1983.

Example:
    "small": (op: "filter.pyr_down", inputs: { "image": "card.image" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to reduce, any pixel format.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The reduced image, ⌈w/2⌉ × ⌈h/2⌉, in the input's pixel format.",
        )]
    }

    fn new(_: NoParams) -> Result<Self, String> {
        Ok(PyrDown)
    }
}

impl Operator for PyrDown {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = pyr_down(image).map_err(|e| OpError::input("image", e))?;
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

params! {
    /// Parameters of `filter.pyr_up`.
    pub struct PyrUpParams {
        /// Output size `[width, height]` in pixels; each side must be twice the input's or one
        /// less (OpenCV's rule). Default: none, twice the input size.
        size: Option<[u32; 2]> = None,
    }
}

/// One step up the Gaussian pyramid (`filter.pyr_up`). See [`pyr_up`].
#[derive(Debug, Clone, PartialEq)]
pub struct PyrUp {
    size: Option<[usize; 2]>,
}

impl Op for PyrUp {
    type Params = PyrUpParams;
    const ID: &'static str = "filter.pyr_up";
    const SUMMARY: &'static str = "Doubles an image's size and smooths it with a 5×5 Gaussian.";
    const DOC: &'static str = r#"
One step up a Gaussian pyramid, as OpenCV's `cv::pyrUp`: zero rows and columns are inserted
after every row and column and the result is convolved with 4 × the 5×5 kernel
[1 4 6 4 1]ᵀ[1 4 6 4 1] / 256 (reflect-101 on the doubled grid). The output is 2w × 2h, or
`size` when given (each side 2w or 2w − 1), in the input's pixel format.

Numerics: u8 and u16 sum exactly in integers and round once, `(s + 32) ≫ 6`, so u8 output is
bit-identical to OpenCV's; f32 sums in f32.

Reference: OpenCV `cv::pyrUp`; P. Burt and E. Adelson, "The Laplacian pyramid as a compact
image code", IEEE Trans. Communications 1983.

Example:
    "big": (op: "filter.pyr_up", inputs: { "image": "small.image" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to expand, any pixel format.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The expanded image, in the input's pixel format.",
        )]
    }

    fn new(params: PyrUpParams) -> Result<Self, String> {
        if let Some([w, h]) = params.size
            && (w == 0 || h == 0 || w > 1 << 16 || h > 1 << 16)
        {
            return Err(format!(
                "`size` must be between 1 and 65536 px per side, got {w}×{h}"
            ));
        }
        Ok(PyrUp {
            size: params.size.map(|[w, h]| [w as usize, h as usize]),
        })
    }
}

impl Operator for PyrUp {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let [w, h] = self.size.unwrap_or([2 * image.width(), 2 * image.height()]);
        let out = pyr_up(image, w, h).map_err(|e| OpError::input("image", e))?;
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

param_enum! {
    /// Which pyramid `filter.pyramid` builds.
    pub enum PyramidKind {
        /// Gaussian: level 0 is the input, level i + 1 = pyr_down(level i).
        Gaussian = "gaussian",
        /// Laplacian: level i = Gᵢ − pyr_up(Gᵢ₊₁) (f32), the last level the coarsest Gᵢ.
        Laplacian = "laplacian",
    }
}

params! {
    /// Parameters of `filter.pyramid`.
    pub struct PyramidParams {
        /// Gaussian or Laplacian pyramid. Default: gaussian.
        kind: PyramidKind = PyramidKind::Gaussian,
        /// Number of levels in the output list, level 0 at full size (1..=32). Default: 4.
        levels: u32 = 4,
    }
}

/// Gaussian or Laplacian pyramid (`filter.pyramid`). See [`gaussian_pyramid`] and
/// [`laplacian_pyramid`].
#[derive(Debug, Clone, PartialEq)]
pub struct Pyramid {
    kind: PyramidKind,
    levels: usize,
}

impl Op for Pyramid {
    type Params = PyramidParams;
    const ID: &'static str = "filter.pyramid";
    const SUMMARY: &'static str = "Builds a Gaussian or Laplacian image pyramid.";
    const DOC: &'static str = r#"
Builds an image pyramid of `levels` images, level 0 at full size and each next level
⌈w/2⌉ × ⌈h/2⌉.

Gaussian: level 0 is the input and level i + 1 = `pyr_down`(level i), in the input's pixel
format (OpenCV's `cv::buildPyramid`).

Laplacian (Burt & Adelson): level i = Gᵢ − `pyr_up`(Gᵢ₊₁) as f32 for i < levels − 1, and the
last level is the coarsest Gaussian level in the input's pixel format. Gᵢ₊₁ and its `pyr_up`
are computed in the input's depth (rounded like OpenCV for integers), so integer images give
exact integer differences and `filter.pyramid_reconstruct` returns the input bit-exactly.

Reference: P. Burt and E. Adelson, "The Laplacian pyramid as a compact image code", IEEE Trans.
Communications 1983; OpenCV `cv::buildPyramid`, `cv::pyrDown`, `cv::pyrUp`.

Example:
    "pyr": (op: "filter.pyramid", inputs: { "image": "card.image" }, params: (kind: laplacian, levels: 5)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to decompose, any pixel format.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "levels",
            PortType::Image.list_of(),
            "The pyramid levels, finest first.",
        )]
    }

    fn new(params: PyramidParams) -> Result<Self, String> {
        if !(1..=MAX_LEVELS).contains(&params.levels) {
            return Err(format!(
                "`levels` must be between 1 and {MAX_LEVELS}, got {}",
                params.levels
            ));
        }
        Ok(Pyramid {
            kind: params.kind,
            levels: params.levels as usize,
        })
    }
}

impl Operator for Pyramid {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let levels = match self.kind {
            PyramidKind::Gaussian => gaussian_pyramid(image, self.levels),
            PyramidKind::Laplacian => laplacian_pyramid(image, self.levels),
        }
        .map_err(|e| OpError::input("image", e))?;
        let items = levels.into_iter().map(Value::image).collect();
        Ok(Outputs::new().with("levels", Value::list(PortType::Image, items)))
    }
}

/// Rebuilds an image from its Laplacian pyramid (`filter.pyramid_reconstruct`). See
/// [`reconstruct`].
#[derive(Debug, Clone, PartialEq)]
pub struct PyramidReconstruct;

impl Op for PyramidReconstruct {
    type Params = NoParams;
    const ID: &'static str = "filter.pyramid_reconstruct";
    const SUMMARY: &'static str = "Rebuilds an image from its Laplacian pyramid.";
    const DOC: &'static str = r#"
Inverts `filter.pyramid` with kind laplacian: starting from the last (coarsest) level G,
G ← Lᵢ + `pyr_up`(G) for i from the second-to-last level down to 0. `pyr_up` and the sum are
done in the last level's depth (rounded and saturated for integers), so a pyramid of an
integer image reconstructs it bit-exactly, and an f32 one within f32 rounding (≈ 1e-6
relative).

Reference: P. Burt and E. Adelson, "The Laplacian pyramid as a compact image code", IEEE Trans.
Communications 1983.

Example:
    "back": (op: "filter.pyramid_reconstruct", inputs: { "levels": "pyr.levels" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "levels",
            PortType::Image.list_of(),
            "A Laplacian pyramid as built by filter.pyramid (f32 levels, then the coarsest level).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The reconstructed image, in the last level's pixel format.",
        )]
    }

    fn new(_: NoParams) -> Result<Self, String> {
        Ok(PyramidReconstruct)
    }
}

impl Operator for PyramidReconstruct {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let list = match inputs.require("levels")? {
            Value::List(list) => list,
            other => {
                return Err(OpError::input(
                    "levels",
                    format!("expected List<Image>, got {}", other.port_type()),
                ));
            }
        };
        let mut images = Vec::with_capacity(list.items.len());
        for (i, item) in list.items.iter().enumerate() {
            match item {
                Value::Image(image) => images.push(image.as_ref().clone()),
                other => {
                    return Err(OpError::input(
                        "levels",
                        format!("item {i} is {}, not an Image", other.port_type()),
                    ));
                }
            }
        }
        let image = reconstruct(&images).map_err(|e| OpError::input("levels", e))?;
        Ok(Outputs::new().with("image", Value::image(image)))
    }
}

/// Accumulator arithmetic of one sample type: exact u32 for integers, f32 for f32.
trait PyrSample: Copy + Default + Send + Sync + 'static {
    type Acc: Copy + Default + Send + Sync + Add<Output = Self::Acc> + Mul<Output = Self::Acc>;
    fn widen(self) -> Self::Acc;
    fn k(v: u8) -> Self::Acc;
    /// `acc / 2^shift`, rounded half up for integers.
    fn finish(acc: Self::Acc, shift: u32) -> Self;
}

/// u8 sums fit 16 bits: pyr_down's are at most 256 · 255 + 128 and pyr_up's 64 · 255 + 32, so
/// both passes run in 16-bit lanes.
impl PyrSample for u8 {
    type Acc = u16;
    #[inline]
    fn widen(self) -> u16 {
        u16::from(self)
    }
    #[inline]
    fn k(v: u8) -> u16 {
        u16::from(v)
    }
    #[inline]
    fn finish(acc: u16, shift: u32) -> u8 {
        ((acc + (1 << (shift - 1))) >> shift) as u8
    }
}

impl PyrSample for u16 {
    type Acc = u32;
    #[inline]
    fn widen(self) -> u32 {
        u32::from(self)
    }
    #[inline]
    fn k(v: u8) -> u32 {
        u32::from(v)
    }
    #[inline]
    fn finish(acc: u32, shift: u32) -> u16 {
        ((acc + (1 << (shift - 1))) >> shift) as u16
    }
}

impl PyrSample for f32 {
    type Acc = f32;
    #[inline]
    fn widen(self) -> f32 {
        self
    }
    #[inline]
    fn k(v: u8) -> f32 {
        f32::from(v)
    }
    #[inline]
    fn finish(acc: f32, shift: u32) -> f32 {
        acc * (1.0 / (1u32 << shift) as f32)
    }
}

/// One Gaussian pyramid step down, as `cv::pyrDown`: 5×5 binomial blur (reflect-101), even rows
/// and columns kept; output ⌈w/2⌉ × ⌈h/2⌉. An empty image gives an empty image.
pub fn pyr_down(image: &Image) -> Result<Image, String> {
    let (w, h) = (image.width(), image.height());
    let (dw, dh) = (w.div_ceil(2), h.div_ceil(2));
    let c = image.channels().count();
    let data = match image.data() {
        PixelData::U8(v) => PixelData::U8(down(v, w, h, c)),
        PixelData::U16(v) => PixelData::U16(down(v, w, h, c)),
        PixelData::F32(v) => PixelData::F32(down(v, w, h, c)),
    };
    Image::new(dw, dh, image.channels(), data).map_err(|e| e.to_string())
}

fn down<T: PyrSample>(src: &[T], w: usize, h: usize, c: usize) -> Vec<T> {
    let (dw, dh) = (w.div_ceil(2), h.div_ceil(2));
    let n = dw * c;
    let sn = w * c;
    let mut dst = ocellus_engine::buffer::zeroed::<T>(n * dh);
    if n == 0 || dh == 0 {
        return dst;
    }
    // Padded column sources: extended position p reads source column cols[p] (p = x + 2); one
    // position more than the window needs, so both deinterleaved halves have `dw + 2` pixels.
    let padded_len = 2 * (dw + 2);
    let cols: Vec<usize> = (0..padded_len)
        .map(|p| map_index(p as isize - 2, w, BorderMode::Reflect101).unwrap_or(0))
        .collect();
    let (k4, k6) = (T::k(4), T::k(6));
    dst.par_chunks_mut(n * BAND_ROWS)
        .enumerate()
        .for_each(|(band, out)| {
            let y0 = band * BAND_ROWS;
            let rows_out = out.len() / n;
            // Horizontal results of source rows 2·y0 − 2 ..= 2·(y0 + rows_out − 1) + 2.
            let count = 2 * rows_out + 3;
            let mut hbuf = vec![T::Acc::default(); count * n];
            let mut padded = vec![T::Acc::default(); padded_len * c];
            // Even and odd extended positions, so the 5-tap window becomes contiguous slices:
            // out[x] = e[x] + 4·o[x] + 6·e[x+1] + 4·o[x+1] + e[x+2].
            let mut even = vec![T::Acc::default(); (dw + 2) * c];
            let mut odd = vec![T::Acc::default(); (dw + 2) * c];
            for (r, hrow) in hbuf.chunks_exact_mut(n).enumerate() {
                let sy =
                    map_index((2 * y0 + r) as isize - 2, h, BorderMode::Reflect101).unwrap_or(0);
                let row = &src[sy * sn..(sy + 1) * sn];
                let inside = (w * c).min(padded.len() - 2 * c);
                for (p, &s) in padded[2 * c..2 * c + inside].iter_mut().zip(row) {
                    *p = s.widen();
                }
                for p in (0..2).chain(w + 2..padded_len) {
                    let sx = cols[p];
                    for ch in 0..c {
                        padded[p * c + ch] = row[sx * c + ch].widen();
                    }
                }
                match c {
                    1 => deinterleave::<T::Acc, 1>(&padded, &mut even, &mut odd),
                    3 => deinterleave::<T::Acc, 3>(&padded, &mut even, &mut odd),
                    _ => deinterleave::<T::Acc, 4>(&padded, &mut even, &mut odd),
                }
                let (e0, e1, e2) = (&even[..n], &even[c..c + n], &even[2 * c..2 * c + n]);
                let (o0, o1) = (&odd[..n], &odd[c..c + n]);
                for (j, hv) in hrow.iter_mut().enumerate() {
                    *hv = e0[j] + e2[j] + (o0[j] + o1[j]) * k4 + e1[j] * k6;
                }
            }
            for (i, line) in out.chunks_exact_mut(n).enumerate() {
                let r = |k: usize| &hbuf[(2 * i + k) * n..(2 * i + k + 1) * n];
                let (a, b, m, d, e) = (r(0), r(1), r(2), r(3), r(4));
                for (j, o) in line.iter_mut().enumerate() {
                    let s = a[j] + e[j] + (b[j] + d[j]) * k4 + m[j] * k6;
                    *o = T::finish(s, 8);
                }
            }
        });
    dst
}

/// Splits the pixels of `padded` into the even-numbered (`even`) and odd-numbered (`odd`) ones.
#[inline]
fn deinterleave<A: Copy, const C: usize>(padded: &[A], even: &mut [A], odd: &mut [A]) {
    for ((pair, e), o) in padded
        .chunks_exact(2 * C)
        .zip(even.chunks_exact_mut(C))
        .zip(odd.chunks_exact_mut(C))
    {
        // C is a constant: these copies are inlined, not memcpy calls.
        e.copy_from_slice(&pair[..C]);
        o.copy_from_slice(&pair[C..]);
    }
}

/// One Gaussian pyramid step up, as `cv::pyrUp`: zeros inserted after every row and column,
/// then 4 × the 5×5 binomial blur (reflect-101 on the doubled grid); output `dw × dh`, where
/// each side must be twice the input's or one less. An empty image gives an empty image.
pub fn pyr_up(image: &Image, dw: usize, dh: usize) -> Result<Image, String> {
    let (w, h) = (image.width(), image.height());
    let fits = |d: usize, s: usize| d == 2 * s || (s > 0 && d + 1 == 2 * s);
    if !fits(dw, w) || !fits(dh, h) {
        return Err(format!(
            "pyr_up of a {w}×{h} image needs an output of {}×{} (or one less per side), got {dw}×{dh}",
            2 * w,
            2 * h
        ));
    }
    let c = image.channels().count();
    let data = match image.data() {
        PixelData::U8(v) => PixelData::U8(up(v, w, h, c, dw, dh)),
        PixelData::U16(v) => PixelData::U16(up(v, w, h, c, dw, dh)),
        PixelData::F32(v) => PixelData::F32(up(v, w, h, c, dw, dh)),
    };
    Image::new(dw, dh, image.channels(), data).map_err(|e| e.to_string())
}

fn up<T: PyrSample>(src: &[T], w: usize, h: usize, c: usize, dw: usize, dh: usize) -> Vec<T> {
    let n = dw * c;
    let sn = w * c;
    let full = 2 * w * c;
    let mut dst = ocellus_engine::buffer::zeroed::<T>(n * dh);
    if n == 0 || dh == 0 {
        return dst;
    }
    // Source row (or column) read at index i ∈ [−1, len]: reflect before, replicate after (the
    // reflect-101 border of the zero-inserted grid).
    let at = |i: isize, len: usize| -> usize {
        if i < 0 {
            map_index(i, len, BorderMode::Reflect101).unwrap_or(0)
        } else {
            (i as usize).min(len - 1)
        }
    };
    let (left, right) = (at(-1, w), at(w as isize, w));
    let (k1, k4, k6) = (T::k(1), T::k(4), T::k(6));
    // Bands of output row pairs: each band covers source rows y0 .. y0 + BAND_ROWS / 2.
    let pairs = BAND_ROWS / 2;
    dst.par_chunks_mut(n * BAND_ROWS)
        .enumerate()
        .for_each(|(band, out)| {
            let y0 = band * pairs;
            let rows_out = out.len() / n;
            let pairs_here = rows_out.div_ceil(2);
            // Horizontal results of source rows y0 − 1 ..= y0 + pairs_here.
            let count = pairs_here + 2;
            let mut hbuf = vec![T::Acc::default(); count * full];
            let mut padded = vec![T::Acc::default(); (w + 2) * c];
            for (r, hrow) in hbuf.chunks_exact_mut(full).enumerate() {
                let sy = at((y0 + r) as isize - 1, h);
                let row = &src[sy * sn..(sy + 1) * sn];
                for (ch, p) in padded[..c].iter_mut().enumerate() {
                    *p = row[left * c + ch].widen();
                }
                for (p, &s) in padded[c..(w + 1) * c].iter_mut().zip(row) {
                    *p = s.widen();
                }
                for ch in 0..c {
                    padded[(w + 1) * c + ch] = row[right * c + ch].widen();
                }
                match c {
                    1 => up_row::<T, 1>(&padded, hrow, k1, k4, k6),
                    3 => up_row::<T, 3>(&padded, hrow, k1, k4, k6),
                    _ => up_row::<T, 4>(&padded, hrow, k1, k4, k6),
                }
            }
            for (i, line) in out.chunks_exact_mut(n).enumerate() {
                let p = i / 2;
                let r = |k: usize| &hbuf[(p + k) * full..(p + k) * full + n];
                if i % 2 == 0 {
                    let (a, m, b) = (r(0), r(1), r(2));
                    for (j, o) in line.iter_mut().enumerate() {
                        *o = T::finish((a[j] + b[j]) * k1 + m[j] * k6, 6);
                    }
                } else {
                    let (m, b) = (r(1), r(2));
                    for (j, o) in line.iter_mut().enumerate() {
                        *o = T::finish((m[j] + b[j]) * k4, 6);
                    }
                }
            }
        });
    dst
}

#[inline]
fn up_row<T: PyrSample, const C: usize>(
    padded: &[T::Acc],
    out: &mut [T::Acc],
    k1: T::Acc,
    k4: T::Acc,
    k6: T::Acc,
) {
    for (x, o) in out.chunks_exact_mut(2 * C).enumerate() {
        let p = &padded[x * C..(x + 3) * C];
        for ch in 0..C {
            o[ch] = (p[ch] + p[2 * C + ch]) * k1 + p[C + ch] * k6;
            o[C + ch] = (p[C + ch] + p[2 * C + ch]) * k4;
        }
    }
}

/// The Gaussian pyramid of `image`: `levels` images, level 0 the input itself.
pub fn gaussian_pyramid(image: &Image, levels: usize) -> Result<Vec<Image>, String> {
    let mut out = vec![image.clone()];
    while out.len() < levels {
        let next = match out.last() {
            Some(last) => pyr_down(last)?,
            None => break,
        };
        out.push(next);
    }
    Ok(out)
}

/// The Laplacian pyramid of `image`: levels 0..levels−1 are `Gᵢ − pyr_up(Gᵢ₊₁)` as f32 (with
/// the Gaussian levels and `pyr_up` in the input's depth), the last level is the coarsest
/// Gaussian level in the input's format.
pub fn laplacian_pyramid(image: &Image, levels: usize) -> Result<Vec<Image>, String> {
    let gauss = gaussian_pyramid(image, levels)?;
    let mut out = Vec::with_capacity(gauss.len());
    for pair in gauss.windows(2) {
        let (fine, coarse) = (&pair[0], &pair[1]);
        let expanded = pyr_up(coarse, fine.width(), fine.height())?;
        let diff: Vec<f32> = samples_f32(fine)
            .zip(samples_f32(&expanded))
            .map(|(a, b)| a - b)
            .collect();
        out.push(
            Image::from_f32(fine.width(), fine.height(), fine.channels(), diff)
                .map_err(|e| e.to_string())?,
        );
    }
    if let Some(last) = gauss.last() {
        out.push(last.clone());
    }
    Ok(out)
}

/// Rebuilds the image a Laplacian pyramid came from: `G ← Lᵢ + pyr_up(G)` from the coarsest
/// level down, in the last level's depth (integers rounded and saturated).
pub fn reconstruct(levels: &[Image]) -> Result<Image, String> {
    let Some((last, rest)) = levels.split_last() else {
        return Err("the pyramid has no levels".into());
    };
    let mut current = last.clone();
    for (i, level) in rest.iter().enumerate().rev() {
        if level.channels() != last.channels() {
            return Err(format!(
                "level {i} has {} channels, the last level {}",
                level.channels().name(),
                last.channels().name()
            ));
        }
        let expanded = pyr_up(&current, level.width(), level.height())
            .map_err(|e| format!("level {i} does not fit the next level: {e}"))?;
        let sums = samples_f32(level)
            .zip(samples_f32(&expanded))
            .map(|(a, b)| a + b);
        let data = match expanded.data() {
            PixelData::U8(_) => PixelData::U8(sums.map(|v| v.round_ties_even() as u8).collect()),
            PixelData::U16(_) => PixelData::U16(sums.map(|v| v.round_ties_even() as u16).collect()),
            PixelData::F32(_) => PixelData::F32(sums.collect()),
        };
        current = Image::new(level.width(), level.height(), level.channels(), data)
            .map_err(|e| e.to_string())?;
    }
    Ok(current)
}

/// The samples of an image as f32 (exact for u8 and u16).
fn samples_f32(image: &Image) -> Box<dyn Iterator<Item = f32> + '_> {
    match image.data() {
        PixelData::U8(v) => Box::new(v.iter().map(|&x| f32::from(x))),
        PixelData::U16(v) => Box::new(v.iter().map(|&x| f32::from(x))),
        PixelData::F32(v) => Box::new(v.iter().copied()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::{random_u8, randoms};
    use ocellus_engine::value::Channels;
    use proptest::prelude::*;

    /// The 7×5 pattern `(37x + 91y + 13xy) mod 256`, input of the OpenCV values below.
    fn pattern() -> Image {
        let data = (0..5)
            .flat_map(|y| (0..7).map(move |x| ((x * 37 + y * 91 + x * y * 13) % 256) as u8))
            .collect();
        Image::from_u8(7, 5, Channels::Gray, data).unwrap()
    }

    fn to_f32(image: &Image) -> Image {
        let data = image
            .as_u8()
            .unwrap()
            .iter()
            .map(|&v| f32::from(v))
            .collect();
        Image::from_f32(image.width(), image.height(), image.channels(), data).unwrap()
    }

    /// Direct definition of pyrDown in f64: 5×5 binomial weights, reflect-101.
    fn reference_down(image: &Image) -> Vec<f64> {
        let (w, h, c) = (image.width(), image.height(), image.channels().count());
        let src: Vec<f64> = samples_f32(image).map(f64::from).collect();
        let k = [1.0, 4.0, 6.0, 4.0, 1.0];
        let mut out = Vec::new();
        for y in 0..h.div_ceil(2) {
            for x in 0..w.div_ceil(2) {
                for ch in 0..c {
                    let mut acc = 0.0;
                    for (j, kj) in k.iter().enumerate() {
                        let sy =
                            map_index((2 * y + j) as isize - 2, h, BorderMode::Reflect101).unwrap();
                        for (i, ki) in k.iter().enumerate() {
                            let sx = map_index((2 * x + i) as isize - 2, w, BorderMode::Reflect101)
                                .unwrap();
                            acc += kj * ki * src[(sy * w + sx) * c + ch];
                        }
                    }
                    out.push(acc / 256.0);
                }
            }
        }
        out
    }

    #[test]
    fn pyr_down_matches_opencv() {
        // cv2.pyrDown(pattern), OpenCV 5.0.
        let out = pyr_down(&pattern()).unwrap();
        assert_eq!((out.width(), out.height()), (4, 3));
        assert_eq!(
            out.as_u8().unwrap(),
            &[99, 132, 133, 142, 135, 143, 143, 143, 115, 134, 141, 136]
        );
    }

    #[test]
    fn pyr_up_matches_opencv() {
        // cv2.pyrUp(pattern) and cv2.pyrUp(pattern, dstsize=(13, 9)), OpenCV 5.0.
        let expected: [u8; 140] = [
            33, 43, 63, 83, 103, 123, 136, 132, 128, 140, 160, 180, 195, 200, 56, 67, 89, 111, 133,
            154, 160, 134, 108, 113, 135, 157, 173, 179, 104, 116, 137, 150, 163, 184, 185, 138,
            91, 92, 113, 126, 133, 135, 151, 165, 177, 157, 138, 150, 162, 142, 123, 135, 147, 127,
            100, 92, 166, 182, 189, 149, 108, 116, 139, 147, 154, 178, 185, 145, 96, 80, 117, 134,
            153, 140, 127, 145, 164, 151, 138, 156, 175, 162, 140, 133, 68, 87, 117, 131, 145, 175,
            189, 155, 117, 119, 141, 163, 180, 185, 83, 104, 129, 122, 116, 141, 166, 159, 137,
            114, 107, 132, 163, 174, 118, 140, 156, 116, 75, 91, 131, 162, 166, 122, 82, 97, 130,
            141, 130, 153, 165, 114, 62, 75, 119, 164, 176, 125, 73, 86, 119, 130,
        ];
        let out = pyr_up(&pattern(), 14, 10).unwrap();
        assert_eq!(out.as_u8().unwrap(), &expected);
        // An odd size is the top-left crop of the full result (as OpenCV).
        let odd = pyr_up(&pattern(), 13, 9).unwrap();
        let cropped: Vec<u8> = expected
            .chunks(14)
            .take(9)
            .flat_map(|r| r[..13].to_vec())
            .collect();
        assert_eq!(odd.as_u8().unwrap(), cropped.as_slice());
        assert!(pyr_up(&pattern(), 12, 10).is_err());
        assert!(pyr_up(&pattern(), 14, 11).is_err());
    }

    #[test]
    fn pyr_down_matches_definition() {
        for (w, h) in [(1, 1), (2, 3), (9, 4), (33, 17)] {
            for channels in [Channels::Gray, Channels::Rgb, Channels::Rgba] {
                let image = random_u8(w, h, channels, (w * h) as u64);
                let expected = reference_down(&image);
                let ours = pyr_down(&image).unwrap();
                for (&a, &e) in ours.as_u8().unwrap().iter().zip(&expected) {
                    // (s + 128) >> 8 is round half up.
                    assert_eq!(f64::from(a), (e + 0.5).floor(), "{w}×{h}");
                }
                let float = pyr_down(&to_f32(&image)).unwrap();
                for (&a, &e) in float.as_f32().unwrap().iter().zip(&expected) {
                    assert!((f64::from(a) - e).abs() < 1e-4, "{w}×{h}");
                }
                let wide = Image::from_u16(
                    w,
                    h,
                    channels,
                    image
                        .as_u8()
                        .unwrap()
                        .iter()
                        .map(|&v| u16::from(v) * 257)
                        .collect(),
                )
                .unwrap();
                let ours = pyr_down(&wide).unwrap();
                for (&a, &e) in ours.as_u16().unwrap().iter().zip(&expected) {
                    assert_eq!(f64::from(a), (e * 257.0 + 0.5).floor(), "{w}×{h} u16");
                }
            }
        }
    }

    #[test]
    fn constant_images_stay_constant() {
        let image = Image::from_u8(11, 6, Channels::Rgb, vec![93; 198]).unwrap();
        let down = pyr_down(&image).unwrap();
        assert!(down.as_u8().unwrap().iter().all(|&v| v == 93));
        let up = pyr_up(&image, 22, 12).unwrap();
        assert!(up.as_u8().unwrap().iter().all(|&v| v == 93));
        let f = Image::from_f32(5, 5, Channels::Gray, vec![-2.5; 25]).unwrap();
        assert!(
            pyr_up(&f, 9, 10)
                .unwrap()
                .as_f32()
                .unwrap()
                .iter()
                .all(|&v| v == -2.5)
        );
    }

    #[test]
    fn pyramid_sizes_and_tiny_images() {
        let image = random_u8(37, 20, Channels::Gray, 4);
        let g = gaussian_pyramid(&image, 5).unwrap();
        let sizes: Vec<_> = g.iter().map(|i| (i.width(), i.height())).collect();
        assert_eq!(sizes, [(37, 20), (19, 10), (10, 5), (5, 3), (3, 2)]);
        assert_eq!(g[0], image);
        let l = laplacian_pyramid(&image, 1).unwrap();
        assert_eq!(l, vec![image.clone()]);
        let one = Image::from_u8(1, 1, Channels::Gray, vec![9]).unwrap();
        assert_eq!(pyr_down(&one).unwrap(), one);
        assert_eq!(pyr_up(&one, 2, 2).unwrap().as_u8().unwrap(), &[9; 4]);
        let l = laplacian_pyramid(&one, 4).unwrap();
        assert_eq!(reconstruct(&l).unwrap(), one);
        let empty = Image::from_u8(0, 0, Channels::Rgb, vec![]).unwrap();
        assert!(pyr_down(&empty).unwrap().is_empty());
        assert!(pyr_up(&empty, 0, 0).unwrap().is_empty());
        assert!(reconstruct(&[]).is_err());
    }

    #[test]
    fn laplacian_levels_are_exact_integers_for_u8() {
        let image = random_u8(45, 31, Channels::Rgb, 6);
        let l = laplacian_pyramid(&image, 4).unwrap();
        assert_eq!(l.len(), 4);
        for level in &l[..3] {
            assert!(level.as_f32().unwrap().iter().all(|v| v.fract() == 0.0));
        }
        assert!(l[3].as_u8().is_some());
    }

    #[test]
    fn output_is_identical_for_any_thread_count() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let image = random_u8(201, 150, Channels::Rgb, 2);
        let run = || laplacian_pyramid(&image, 4).unwrap();
        assert_eq!(pool(1).install(run), pool(3).install(run));
    }

    #[test]
    fn operators_build_lists() {
        let op = Pyramid::new(PyramidParams {
            kind: PyramidKind::Laplacian,
            levels: 3,
        })
        .unwrap();
        assert_eq!(op.levels, 3);
        assert!(
            Pyramid::new(PyramidParams {
                kind: PyramidKind::Gaussian,
                levels: 0,
            })
            .is_err()
        );
        assert!(PyrUp::new(PyrUpParams { size: Some([0, 4]) }).is_err());
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(40))]

        #[test]
        fn laplacian_reconstructs_u8_exactly(
            w in 1usize..40, h in 1usize..40, levels in 1usize..6, seed in 0u64..1000,
            c in prop::sample::select(vec![Channels::Gray, Channels::Rgb, Channels::Rgba]),
        ) {
            let image = random_u8(w, h, c, seed);
            let l = laplacian_pyramid(&image, levels).unwrap();
            prop_assert_eq!(reconstruct(&l).unwrap(), image);
        }

        #[test]
        fn laplacian_reconstructs_f32(
            w in 1usize..40, h in 1usize..40, levels in 1usize..6, seed in 0u64..1000,
        ) {
            let data: Vec<f32> = randoms(seed, w * h).iter().map(|&r| r as f32).collect();
            let image = Image::from_f32(w, h, Channels::Gray, data).unwrap();
            let l = laplacian_pyramid(&image, levels).unwrap();
            let back = reconstruct(&l).unwrap();
            for (a, b) in back.as_f32().unwrap().iter().zip(image.as_f32().unwrap()) {
                prop_assert!((a - b).abs() <= 1e-5, "{} vs {}", a, b);
            }
        }
    }
}
