//! `filter.erode`, `filter.dilate` and `filter.morphology`: grayscale morphology with OpenCV's
//! `erode` / `dilate` / `morphologyEx` semantics, per channel, on u8, u16 and f32 images.
//!
//! Erosion is the minimum and dilation the maximum of the samples under a structuring element
//! placed with its anchor on the output pixel: `erode(x, y) = min { in(x + i − ax, y + j − ay) :
//! (i, j) ∈ element }`, with anchor `(ax, ay)`, by default `(⌊w/2⌋, ⌊h/2⌋)`. Dilation uses the same
//! element and anchor, not its reflection, exactly as OpenCV.
//!
//! How it runs:
//! - Each row of an element is a few horizontal runs of ones (one for rectangles, crosses and
//!   ellipses; any number for a custom mask). Rows holding the same run are grouped, and each
//!   group is widened to the longest interval of consecutive element rows whose runs contain
//!   that run (adding such rows cannot change a minimum over the group). A rectangle is one group; a cross is two (its full middle row and
//!   its full column); an ellipse is one nested rectangle per distinct row width.
//! - A group `(run, rows j0..j1)` is a separable window: the 1-D extremum of each padded source
//!   row over the run, then the 1-D extremum of those results over `j1 − j0` rows. The output is
//!   the extremum over the groups.
//! - Each 1-D extremum over `k` samples is computed in time independent of `k` by the van Herk /
//!   Gil-Werman algorithm: the line is cut into blocks of `k`; within each block a running
//!   extremum from the left (prefix) and from the right (suffix) is taken; the window starting at
//!   `i` is then `op(suffix[i], prefix[i + k − 1])`, three comparisons per sample whatever `k`.
//!   Windows of at most [`DIRECT_MAX_TAPS`] samples take the extremum of shifted slices
//!   directly, which vectorizes and is faster there. Both give identical results (min and max are
//!   exact).
//! - The image is cut into fixed bands of rows processed in parallel (`par_chunks_mut`); band
//!   boundaries do not depend on the thread count, so outputs are bit-identical for any thread
//!   count.
//! - Borders: `neutral` (the default) reads +max for erosion and −max for dilation (+∞ / −∞ for
//!   f32), so pixels outside the image never win, like OpenCV's `morphologyDefaultBorderValue`;
//!   the other modes go through [`BorderTable`].
//!
//! NaN in f32 input gives deterministic but unspecified results in windows containing it.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::border::{BorderMode, BorderTable};

/// Largest structuring element side, px.
pub const MAX_KSIZE: u32 = 1023;

/// Largest iteration count.
pub const MAX_ITERATIONS: u32 = 255;

/// Windows up to this many samples take the extremum of shifted slices directly; longer ones use
/// van Herk / Gil-Werman.
pub const DIRECT_MAX_TAPS: usize = 8;

/// Windows up to this many samples along rows of few channels use doubling (see [`doubling`]);
/// longer ones van Herk / Gil-Werman.
pub const DOUBLING_MAX_TAPS: usize = 64;

/// Strides from which the van Herk recurrences run over whole slices (rows) instead of single
/// samples.
const WIDE_STRIDE: usize = 16;

/// Output rows per parallel band (at least; tall elements get taller bands so that the
/// `ksize_y − 1` rows of overlap recomputed per band stay cheap).
const BAND_ROWS: usize = 32;

param_enum! {
    /// Structuring element shapes (OpenCV's `MorphShapes` of `getStructuringElement`).
    pub enum Shape {
        /// All ones (`MORPH_RECT`).
        Rect = "rect",
        /// The middle row and the middle column (`MORPH_CROSS`).
        Cross = "cross",
        /// The ellipse inscribed in the `width × height` box (`MORPH_ELLIPSE`).
        Ellipse = "ellipse",
    }
}

param_enum! {
    /// How morphology reads pixels outside the image.
    pub enum MorphBorder {
        /// Outside pixels never affect the result: +max for erosion, −max for dilation
        /// (OpenCV's default, `BORDER_CONSTANT` with `morphologyDefaultBorderValue`).
        Neutral = "neutral",
        /// Repeat the edge pixel (`BORDER_REPLICATE`).
        Clamp = "clamp",
        /// Mirror, repeating the edge pixel (`BORDER_REFLECT`).
        Reflect = "reflect",
        /// Mirror about the edge pixel (`BORDER_REFLECT_101`).
        Reflect101 = "reflect_101",
        /// Periodic (`BORDER_WRAP`).
        Wrap = "wrap",
    }
}

param_enum! {
    /// Compound morphological operations (OpenCV's `MorphTypes`).
    pub enum Operation {
        /// `dilate(erode(src))` (`MORPH_OPEN`).
        Open = "open",
        /// `erode(dilate(src))` (`MORPH_CLOSE`).
        Close = "close",
        /// `dilate(src) − erode(src)` (`MORPH_GRADIENT`).
        Gradient = "gradient",
        /// `src − open(src)` (`MORPH_TOPHAT`).
        Tophat = "tophat",
        /// `close(src) − src` (`MORPH_BLACKHAT`).
        Blackhat = "blackhat",
    }
}

impl MorphBorder {
    /// The [`BorderMode`] the border tables use; `neutral` is a constant border whose value is
    /// the neutral element of the operation.
    pub fn border_mode(self) -> BorderMode {
        match self {
            MorphBorder::Neutral => BorderMode::Constant,
            MorphBorder::Clamp => BorderMode::Clamp,
            MorphBorder::Reflect => BorderMode::Reflect,
            MorphBorder::Reflect101 => BorderMode::Reflect101,
            MorphBorder::Wrap => BorderMode::Wrap,
        }
    }
}

/// A structuring element with one horizontal run of ones per row (or none), and its anchor.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StructuringElement {
    width: usize,
    height: usize,
    anchor_x: usize,
    anchor_y: usize,
    /// Per row: `(first column, length)` of each maximal run of ones, left to right (empty for
    /// a row without ones).
    runs: Vec<Vec<(usize, usize)>>,
}

impl StructuringElement {
    /// The element of `shape` in a `width × height` box, anchored at its centre
    /// `(⌊width/2⌋, ⌊height/2⌋)` as OpenCV's `getStructuringElement`; `None` for a zero side.
    ///
    /// The ellipse has, in row `i`, the ones `|x − c| ≤ round(c · √(1 − (i − r)²/r²))` with
    /// `c = ⌊width/2⌋`, `r = ⌊height/2⌋` (only the centre pixel when `r = 0`), clipped to the box.
    pub fn new(shape: Shape, width: usize, height: usize) -> Option<StructuringElement> {
        if width == 0 || height == 0 {
            return None;
        }
        let (c, r) = (width / 2, height / 2);
        let runs = (0..height)
            .map(|i| match shape {
                Shape::Rect => vec![(0, width)],
                Shape::Cross if i == r => vec![(0, width)],
                Shape::Cross => vec![(c, 1)],
                Shape::Ellipse => {
                    let dy = i as f64 - r as f64;
                    // OpenCV takes the ratio as 0 for a one-row box: only the centre pixel.
                    let fraction = if r == 0 {
                        0.0
                    } else {
                        (1.0 - dy * dy / (r * r) as f64).max(0.0)
                    };
                    let dx = (c as f64 * fraction.sqrt()).round() as usize;
                    let first = c.saturating_sub(dx);
                    let end = (c + dx + 1).min(width);
                    vec![(first, end - first)]
                }
            })
            .collect();
        Some(StructuringElement {
            width,
            height,
            anchor_x: c,
            anchor_y: r,
            runs,
        })
    }

    /// A `width × height` rectangle with an explicit anchor (inside the box).
    fn rect_with_anchor(
        width: usize,
        height: usize,
        anchor_x: usize,
        anchor_y: usize,
    ) -> StructuringElement {
        StructuringElement {
            width,
            height,
            anchor_x: anchor_x.min(width.saturating_sub(1)),
            anchor_y: anchor_y.min(height.saturating_sub(1)),
            runs: vec![vec![(0, width)]; height],
        }
    }

    /// Any element: `mask[y][x]` nonzero marks the cell `(x, y)` of a box as wide as the longest
    /// row (shorter rows are padded with zeros), anchored at `anchor` or at the box centre
    /// `(⌊width/2⌋, ⌊height/2⌋)`. Errors on an empty mask, a mask without ones, a box side over
    /// [`MAX_KSIZE`] or an anchor outside the box.
    pub fn from_mask(
        mask: &[Vec<u8>],
        anchor: Option<(usize, usize)>,
    ) -> Result<StructuringElement, String> {
        let height = mask.len();
        let width = mask.iter().map(Vec::len).max().unwrap_or(0);
        if width == 0 || height == 0 {
            return Err("the structuring element mask is empty".into());
        }
        let max = MAX_KSIZE as usize;
        if width > max || height > max {
            return Err(format!(
                "the structuring element mask is {width}×{height}; each side must be at most {max}"
            ));
        }
        let runs: Vec<Vec<(usize, usize)>> = mask
            .iter()
            .map(|row| {
                let mut runs = Vec::new();
                let mut x = 0;
                while x < row.len() {
                    if row[x] == 0 {
                        x += 1;
                        continue;
                    }
                    let start = x;
                    while x < row.len() && row[x] != 0 {
                        x += 1;
                    }
                    runs.push((start, x - start));
                }
                runs
            })
            .collect();
        if runs.iter().all(Vec::is_empty) {
            return Err("the structuring element mask has no nonzero cell".into());
        }
        let (anchor_x, anchor_y) = anchor.unwrap_or((width / 2, height / 2));
        if anchor_x >= width || anchor_y >= height {
            return Err(format!(
                "anchor ({anchor_x}, {anchor_y}) lies outside the {width}×{height} element"
            ));
        }
        Ok(StructuringElement {
            width,
            height,
            anchor_x,
            anchor_y,
            runs,
        })
    }

    /// The same element with its anchor moved to `(x, y)`; errors when outside the box.
    pub fn with_anchor(mut self, x: usize, y: usize) -> Result<StructuringElement, String> {
        if x >= self.width || y >= self.height {
            return Err(format!(
                "anchor ({x}, {y}) lies outside the {}×{} element",
                self.width, self.height
            ));
        }
        self.anchor_x = x;
        self.anchor_y = y;
        Ok(self)
    }

    /// The element reflected through its anchor (cells `(x, y)` → `(w − 1 − x, h − 1 − y)`, anchor
    /// `(w − 1 − ax, h − 1 − ay)`).
    pub fn reflected(&self) -> StructuringElement {
        let (w, h) = (self.width, self.height);
        let mask: Vec<Vec<u8>> = (0..h)
            .rev()
            .map(|y| {
                (0..w)
                    .rev()
                    .map(|x| u8::from(self.contains(x, y)))
                    .collect()
            })
            .collect();
        StructuringElement {
            width: w,
            height: h,
            anchor_x: w - 1 - self.anchor_x,
            anchor_y: h - 1 - self.anchor_y,
            runs: Self::from_mask(&mask, None)
                .map(|e| e.runs)
                .unwrap_or_else(|_| self.runs.clone()),
        }
    }

    /// The offsets `(dx, dy)` of the element's cells relative to the anchor, row by row.
    pub fn offsets(&self) -> Vec<(isize, isize)> {
        let mut out = Vec::new();
        for (y, runs) in self.runs.iter().enumerate() {
            for &(first, len) in runs {
                for x in first..first + len {
                    out.push((
                        x as isize - self.anchor_x as isize,
                        y as isize - self.anchor_y as isize,
                    ));
                }
            }
        }
        out
    }

    /// Box width.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Box height.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Anchor `(x, y)` inside the box.
    pub fn anchor(&self) -> (usize, usize) {
        (self.anchor_x, self.anchor_y)
    }

    /// Whether the element holds the box cell `(x, y)`.
    pub fn contains(&self, x: usize, y: usize) -> bool {
        self.runs.get(y).is_some_and(|runs| {
            runs.iter()
                .any(|&(first, len)| (first..first + len).contains(&x))
        })
    }

    /// True when every cell of the box is set.
    pub fn is_full(&self) -> bool {
        self.runs.iter().all(|runs| runs[..] == [(0, self.width)])
    }

    /// The separable groups: `(run, first row, rows)`, see the module docs.
    fn groups(&self) -> Vec<((usize, usize), usize, usize)> {
        let covers = |row: usize, (first, len): (usize, usize)| {
            self.runs[row]
                .iter()
                .any(|&(f, l)| f <= first && first + len <= f + l)
        };
        let mut distinct: Vec<(usize, usize)> = self.runs.iter().flatten().copied().collect();
        distinct.sort_unstable();
        distinct.dedup();
        let mut groups = Vec::new();
        for run in distinct {
            let mut j = 0;
            while j < self.height {
                if !covers(j, run) {
                    j += 1;
                    continue;
                }
                let start = j;
                while j < self.height && covers(j, run) {
                    j += 1;
                }
                if (start..j).any(|k| self.runs[k].contains(&run)) {
                    groups.push((run, start, j - start));
                }
            }
        }
        // A group contained in another (same rows or fewer, run covering) adds nothing.
        let contained = |a: &((usize, usize), usize, usize), b: &((usize, usize), usize, usize)| {
            let ((af, al), aj, an) = *a;
            let ((bf, bl), bj, bn) = *b;
            bf <= af && af + al <= bf + bl && bj <= aj && aj + an <= bj + bn
        };
        let mut kept: Vec<((usize, usize), usize, usize)> = Vec::new();
        for (i, g) in groups.iter().enumerate() {
            let redundant = groups
                .iter()
                .enumerate()
                .any(|(k, h)| k != i && contained(h, g) && (h != g || k < i));
            if !redundant {
                kept.push(*g);
            }
        }
        kept
    }
}

/// A sample type for morphology.
pub trait Sample: Copy + PartialOrd + Default + Send + Sync + 'static {
    /// The smallest value (−∞ for f32): dilation's neutral border.
    const LOWEST: Self;
    /// The largest value (+∞ for f32): erosion's neutral border.
    const HIGHEST: Self;
    /// `self − other`, saturating at 0 for unsigned types.
    fn difference(self, other: Self) -> Self;
}

impl Sample for u8 {
    const LOWEST: u8 = 0;
    const HIGHEST: u8 = u8::MAX;
    fn difference(self, other: u8) -> u8 {
        self.saturating_sub(other)
    }
}

impl Sample for u16 {
    const LOWEST: u16 = 0;
    const HIGHEST: u16 = u16::MAX;
    fn difference(self, other: u16) -> u16 {
        self.saturating_sub(other)
    }
}

impl Sample for f32 {
    const LOWEST: f32 = f32::NEG_INFINITY;
    const HIGHEST: f32 = f32::INFINITY;
    fn difference(self, other: f32) -> f32 {
        self - other
    }
}

/// Minimum (erosion) or maximum (dilation).
trait Extremum: Send + Sync + 'static {
    /// The winner of two samples.
    fn pick<T: Sample>(a: T, b: T) -> T;
    /// The value that never wins.
    fn neutral<T: Sample>() -> T;
}

struct Min;
struct Max;

impl Extremum for Min {
    #[inline(always)]
    fn pick<T: Sample>(a: T, b: T) -> T {
        if b < a { b } else { a }
    }
    fn neutral<T: Sample>() -> T {
        T::HIGHEST
    }
}

impl Extremum for Max {
    #[inline(always)]
    fn pick<T: Sample>(a: T, b: T) -> T {
        if b > a { b } else { a }
    }
    fn neutral<T: Sample>() -> T {
        T::LOWEST
    }
}

params! {
    /// Parameters of `filter.erode` and `filter.dilate`.
    pub struct MorphParams {
        /// Structuring element shape: "rect", "cross" or "ellipse".
        shape: Shape = Shape::Rect,
        /// Structuring element size `[width, height]`, each 1..=1023 (ignored when `element`
        /// is given).
        ksize: [u32; 2] = [3, 3] => [min = 1, max = 1023, unit = "px"],
        /// Custom structuring element, rows of cells (nonzero = part of the element), e.g.
        /// `[[0, 1, 0], [1, 1, 1]]`; shorter rows are padded with zeros. Default `[]`: use
        /// `shape` and `ksize`; when given it replaces them.
        element: Vec<Vec<u8>> = Vec::new(),
        /// Anchor `[x, y]` inside the element box, px; default none: the centre
        /// `(⌊width/2⌋, ⌊height/2⌋)`.
        anchor: Option<[u32; 2]> = None,
        /// Times the operation is applied, 1..=255.
        iterations: u32 = 1 => [min = 1, max = 255],
        /// How pixels outside the image are read; "neutral" lets them never win.
        border: MorphBorder = MorphBorder::Neutral,
    }
}

params! {
    /// Parameters of `filter.morphology`.
    pub struct MorphologyParams {
        /// "open", "close", "gradient", "tophat" or "blackhat".
        operation: Operation = Operation::Open,
        /// Structuring element shape: "rect", "cross" or "ellipse".
        shape: Shape = Shape::Rect,
        /// Structuring element size `[width, height]`, each 1..=1023 (ignored when `element`
        /// is given).
        ksize: [u32; 2] = [3, 3] => [min = 1, max = 1023, unit = "px"],
        /// Custom structuring element, rows of cells (nonzero = part of the element), e.g.
        /// `[[0, 1, 0], [1, 1, 1]]`; shorter rows are padded with zeros. Default `[]`: use
        /// `shape` and `ksize`; when given it replaces them.
        element: Vec<Vec<u8>> = Vec::new(),
        /// Anchor `[x, y]` inside the element box, px; default none: the centre
        /// `(⌊width/2⌋, ⌊height/2⌋)`.
        anchor: Option<[u32; 2]> = None,
        /// Times each erosion and dilation inside the operation is applied, 1..=255.
        iterations: u32 = 1 => [min = 1, max = 255],
        /// How pixels outside the image are read; "neutral" lets them never win.
        border: MorphBorder = MorphBorder::Neutral,
    }
}

/// Checked element and iteration count shared by the three operators.
#[derive(Debug, Clone, PartialEq)]
struct Setup {
    element: StructuringElement,
    iterations: usize,
    border: MorphBorder,
}

impl Setup {
    fn new(
        shape: Shape,
        ksize: [u32; 2],
        element: &[Vec<u8>],
        anchor: Option<[u32; 2]>,
        iterations: u32,
        border: MorphBorder,
    ) -> Result<Setup, String> {
        if !(1..=MAX_ITERATIONS).contains(&iterations) {
            return Err(format!(
                "`iterations` must be between 1 and {MAX_ITERATIONS}, got {iterations}"
            ));
        }
        let anchor = anchor.map(|[x, y]| (x as usize, y as usize));
        if !element.is_empty() {
            return Ok(Setup {
                element: StructuringElement::from_mask(element, anchor)
                    .map_err(|e| format!("`element`: {e}"))?,
                iterations: iterations as usize,
                border,
            });
        }
        for (name, k) in ["width", "height"].iter().zip(ksize) {
            if !(1..=MAX_KSIZE).contains(&k) {
                return Err(format!(
                    "`ksize` {name} must be between 1 and {MAX_KSIZE}, got {k}"
                ));
            }
        }
        let mut element = StructuringElement::new(shape, ksize[0] as usize, ksize[1] as usize)
            .ok_or_else(|| "`ksize` must be at least 1".to_string())?;
        if let Some((x, y)) = anchor {
            element = element
                .with_anchor(x, y)
                .map_err(|e| format!("`anchor`: {e}"))?;
        }
        Ok(Setup {
            element,
            iterations: iterations as usize,
            border,
        })
    }
}

/// Shared operator documentation: element, borders, iterations.
macro_rules! common_doc {
    () => {
        r#"
Structuring elements are OpenCV's `getStructuringElement(shape, ksize)` or any binary mask given
as `element` (rows of 0/1), anchored at `anchor`, by default the centre (⌊w/2⌋, ⌊h/2⌋).
Shapes: "rect" (all ones), "cross" (middle row and column) and "ellipse" (in row i the ones
|x − c| ≤ round(c·√(1 − (i − r)²/r²)), c = ⌊w/2⌋, r = ⌊h/2⌋; one pixel when h = 1).
Border "neutral" (default) means outside pixels never win (OpenCV's `morphologyDefaultBorderValue`); "clamp", "reflect",
"reflect_101" and "wrap" are OpenCV's border types. Like OpenCV, `iterations` > 1 with a full
element (rect) is done in one pass with the equivalent larger rectangle
(k + (iterations − 1)(k − 1), anchor scaled by iterations) when that stays ≤ 1023 px; other
elements are applied repeatedly. Works per channel on every pixel format; the output has the
input's size and format.

Method: separable van Herk / Gil-Werman running extrema (rows, then columns) with prefix and
suffix maxima in blocks of the window length, so a rectangle costs the same whatever its size;
crosses and ellipses are decomposed into a few such rectangles (one per distinct row run).
Deterministic, bit-identical for any thread count.

References: M. van Herk, "A fast algorithm for local minimum and maximum filters on rectangular
and octagonal kernels", Pattern Recognition Letters 13(7), 1992; J. Gil and M. Werman,
"Computing 2-D min, median, and max filters", IEEE PAMI 15(5), 1993; OpenCV `cv::erode`,
`cv::dilate`, `cv::morphologyEx`, `cv::getStructuringElement`.
"#
    };
}

/// Erosion (`filter.erode`): the minimum under the structuring element. See [`erode`].
#[derive(Debug, Clone, PartialEq)]
pub struct Erode {
    setup: Setup,
}

/// Dilation (`filter.dilate`): the maximum under the structuring element. See [`dilate`].
#[derive(Debug, Clone, PartialEq)]
pub struct Dilate {
    setup: Setup,
}

/// Compound morphology (`filter.morphology`): opening, closing, gradient, top-hat, black-hat.
/// See [`morphology`].
#[derive(Debug, Clone, PartialEq)]
pub struct Morphology {
    operation: Operation,
    setup: Setup,
}

fn image_port(doc: &str) -> Vec<PortSpec> {
    vec![PortSpec::new("image", PortType::Image, doc)]
}

const INPUT_DOC: &str = "Image to filter, any pixel format (channels are filtered independently).";
const OUTPUT_DOC: &str = "The filtered image, same size and pixel format as the input.";

impl Op for Erode {
    type Params = MorphParams;
    const ID: &'static str = "filter.erode";
    const SUMMARY: &'static str = "Erodes an image: the minimum under a structuring element.";
    const DOC: &'static str = concat!(
        r#"
Erosion: each output sample is the minimum of the input samples under the structuring element
placed with its anchor on the pixel, as OpenCV's `cv::erode`.
"#,
        common_doc!(),
        r#"
Example:
    "thin": (op: "filter.erode", inputs: { "image": "mask.image" }, params: (shape: "ellipse", ksize: [5, 5])),
"#
    );

    fn inputs() -> Vec<PortSpec> {
        image_port(INPUT_DOC)
    }

    fn outputs() -> Vec<PortSpec> {
        image_port(OUTPUT_DOC)
    }

    fn new(params: MorphParams) -> Result<Self, String> {
        let MorphParams {
            shape,
            ksize,
            element,
            anchor,
            iterations,
            border,
        } = params;
        Ok(Erode {
            setup: Setup::new(shape, ksize, &element, anchor, iterations, border)?,
        })
    }
}

impl Op for Dilate {
    type Params = MorphParams;
    const ID: &'static str = "filter.dilate";
    const SUMMARY: &'static str = "Dilates an image: the maximum under a structuring element.";
    const DOC: &'static str = concat!(
        r#"
Dilation: each output sample is the maximum of the input samples under the structuring element
placed with its anchor on the pixel (the element itself, not its reflection), as OpenCV's
`cv::dilate`.
"#,
        common_doc!(),
        r#"
Example:
    "grow": (op: "filter.dilate", inputs: { "image": "mask.image" }, params: (ksize: [3, 3], iterations: 2)),
"#
    );

    fn inputs() -> Vec<PortSpec> {
        image_port(INPUT_DOC)
    }

    fn outputs() -> Vec<PortSpec> {
        image_port(OUTPUT_DOC)
    }

    fn new(params: MorphParams) -> Result<Self, String> {
        let MorphParams {
            shape,
            ksize,
            element,
            anchor,
            iterations,
            border,
        } = params;
        Ok(Dilate {
            setup: Setup::new(shape, ksize, &element, anchor, iterations, border)?,
        })
    }
}

impl Op for Morphology {
    type Params = MorphologyParams;
    const ID: &'static str = "filter.morphology";
    const SUMMARY: &'static str =
        "Opening, closing, morphological gradient, top-hat or black-hat of an image.";
    const DOC: &'static str = concat!(
        r#"
Compound morphology as OpenCV's `cv::morphologyEx`: "open" = dilate(erode(src)),
"close" = erode(dilate(src)), "gradient" = dilate(src) − erode(src), "tophat" = src − open(src),
"blackhat" = close(src) − src. Each erosion and dilation is applied `iterations` times.
Differences saturate at 0 for u8 and u16 (they are never negative with the default border);
f32 subtracts exactly.
"#,
        common_doc!(),
        r#"
Example:
    "clean": (op: "filter.morphology", inputs: { "image": "mask.image" }, params: (operation: "open", ksize: [5, 5])),
"#
    );

    fn inputs() -> Vec<PortSpec> {
        image_port(INPUT_DOC)
    }

    fn outputs() -> Vec<PortSpec> {
        image_port(OUTPUT_DOC)
    }

    fn new(params: MorphologyParams) -> Result<Self, String> {
        let MorphologyParams {
            operation,
            shape,
            ksize,
            element,
            anchor,
            iterations,
            border,
        } = params;
        Ok(Morphology {
            operation,
            setup: Setup::new(shape, ksize, &element, anchor, iterations, border)?,
        })
    }
}

impl Operator for Erode {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let Setup {
            element,
            iterations,
            border,
        } = &self.setup;
        let out = erode(image, element, *iterations, *border);
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

impl Operator for Dilate {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let Setup {
            element,
            iterations,
            border,
        } = &self.setup;
        let out = dilate(image, element, *iterations, *border);
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

impl Operator for Morphology {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let Setup {
            element,
            iterations,
            border,
        } = &self.setup;
        let out = morphology(image, self.operation, element, *iterations, *border);
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// Erosion of `image` by `element`, applied `iterations` times (0 counts as 1), per channel.
/// See the module docs; empty images are returned unchanged.
pub fn erode(
    image: &Image,
    element: &StructuringElement,
    iterations: usize,
    border: MorphBorder,
) -> Image {
    iterate::<Min>(image, element, iterations, border)
}

/// Dilation of `image` by `element`, applied `iterations` times (0 counts as 1), per channel.
pub fn dilate(
    image: &Image,
    element: &StructuringElement,
    iterations: usize,
    border: MorphBorder,
) -> Image {
    iterate::<Max>(image, element, iterations, border)
}

/// The compound `operation` of `image` (see [`Operation`]), each erosion and dilation applied
/// `iterations` times.
pub fn morphology(
    image: &Image,
    operation: Operation,
    element: &StructuringElement,
    iterations: usize,
    border: MorphBorder,
) -> Image {
    // Opening and closing run both passes in one sweep when one pass does each.
    let fused = |first_min: bool, img: &Image| {
        single_pass(element, iterations).and_then(|e| {
            if first_min {
                apply_fused::<Min, Max>(img, &e, border)
            } else {
                apply_fused::<Max, Min>(img, &e, border)
            }
        })
    };
    let open = |img: &Image| {
        fused(true, img).unwrap_or_else(|| {
            dilate(
                &erode(img, element, iterations, border),
                element,
                iterations,
                border,
            )
        })
    };
    let close = |img: &Image| {
        fused(false, img).unwrap_or_else(|| {
            erode(
                &dilate(img, element, iterations, border),
                element,
                iterations,
                border,
            )
        })
    };
    match operation {
        Operation::Open => open(image),
        Operation::Close => close(image),
        Operation::Gradient => difference(
            dilate(image, element, iterations, border),
            &erode(image, element, iterations, border),
            false,
        ),
        Operation::Tophat => difference(open(image), image, true),
        Operation::Blackhat => difference(close(image), image, false),
    }
}

/// `a − b` per sample, or `b − a` when `reversed` (saturating for unsigned types), written over
/// `a`'s samples; `a` when the formats differ.
fn difference(a: Image, b: &Image, reversed: bool) -> Image {
    fn sub<T: Sample>(a: &mut [T], b: &[T], reversed: bool) {
        if reversed {
            for (x, &y) in a.iter_mut().zip(b) {
                *x = y.difference(*x);
            }
        } else {
            for (x, &y) in a.iter_mut().zip(b) {
                *x = x.difference(y);
            }
        }
    }
    let (width, height, channels) = (a.width(), a.height(), a.channels());
    let mut data = a.into_data();
    match (&mut data, b.data()) {
        (PixelData::U8(x), PixelData::U8(y)) => sub(x, y, reversed),
        (PixelData::U16(x), PixelData::U16(y)) => sub(x, y, reversed),
        (PixelData::F32(x), PixelData::F32(y)) => sub(x, y, reversed),
        _ => {}
    }
    Image::new(width, height, channels, data).unwrap_or_else(|_| b.clone())
}

/// An image of `image`'s size and channels holding `data` (which has the same sample count).
fn same_shape(image: &Image, data: PixelData) -> Image {
    Image::new(image.width(), image.height(), image.channels(), data)
        .unwrap_or_else(|_| image.clone())
}

fn iterate<M: Extremum>(
    image: &Image,
    element: &StructuringElement,
    iterations: usize,
    border: MorphBorder,
) -> Image {
    let iterations = iterations.max(1);
    if image.is_empty() || (element.width == 1 && element.height == 1 && element.is_full()) {
        return image.clone();
    }
    if let Some(single) = single_pass(element, iterations) {
        return apply::<M>(image, &single, border);
    }
    let mut out = apply::<M>(image, element, border);
    for _ in 1..iterations {
        out = apply::<M>(&out, element, border);
    }
    out
}

/// The element one pass of which does `iterations` passes of `element`, if there is one: the
/// element itself for one iteration; for a full rectangle OpenCV's shortcut (n passes of a full
/// k-wide rectangle are one pass of a (k + (n − 1)(k − 1))-wide one with the anchor scaled by n)
/// while that stays within [`MAX_KSIZE`].
fn single_pass(element: &StructuringElement, iterations: usize) -> Option<StructuringElement> {
    if iterations <= 1 {
        return Some(element.clone());
    }
    if !element.is_full() {
        return None;
    }
    let grow = |k: usize| k + (iterations - 1) * (k - 1);
    let (w, h) = (grow(element.width), grow(element.height));
    (w <= MAX_KSIZE as usize && h <= MAX_KSIZE as usize).then(|| {
        StructuringElement::rect_with_anchor(
            w,
            h,
            element.anchor_x * iterations,
            element.anchor_y * iterations,
        )
    })
}

/// `B(A(image))` in one sweep (see [`fused_bands`]); `None` when that does not apply.
fn apply_fused<A: Extremum, B: Extremum>(
    image: &Image,
    element: &StructuringElement,
    border: MorphBorder,
) -> Option<Image> {
    if image.is_empty() {
        return Some(image.clone());
    }
    let data = match image.data() {
        PixelData::U8(src) => PixelData::U8(fused_bands::<A, B, u8>(image, src, element, border)?),
        PixelData::U16(src) => {
            PixelData::U16(fused_bands::<A, B, u16>(image, src, element, border)?)
        }
        PixelData::F32(src) => {
            PixelData::F32(fused_bands::<A, B, f32>(image, src, element, border)?)
        }
    };
    Some(same_shape(image, data))
}

/// One pass of `M` over every sample type.
fn apply<M: Extremum>(image: &Image, element: &StructuringElement, border: MorphBorder) -> Image {
    let data = match image.data() {
        PixelData::U8(src) => PixelData::U8(extremum_bands::<M, u8>(image, src, element, border)),
        PixelData::U16(src) => {
            PixelData::U16(extremum_bands::<M, u16>(image, src, element, border))
        }
        PixelData::F32(src) => {
            PixelData::F32(extremum_bands::<M, f32>(image, src, element, border))
        }
    };
    same_shape(image, data)
}

/// Geometry of one extremum pass over an image: the element's groups and border tables.
struct Pass {
    groups: Vec<((usize, usize), usize, usize)>,
    columns: BorderTable,
    rows: BorderTable,
    /// Samples per image row.
    n: usize,
    channels: usize,
    kh: usize,
}

impl Pass {
    fn new(
        width: usize,
        height: usize,
        channels: usize,
        element: &StructuringElement,
        border: MorphBorder,
    ) -> Pass {
        let (kw, kh) = (element.width, element.height);
        let mode = border.border_mode();
        Pass {
            groups: element.groups(),
            columns: BorderTable::new(width, element.anchor_x, kw - 1 - element.anchor_x, mode),
            rows: BorderTable::new(height, element.anchor_y, kh - 1 - element.anchor_y, mode),
            n: width * channels,
            channels,
            kh,
        }
    }

    /// Rows per parallel band.
    fn band_rows(&self) -> usize {
        BAND_ROWS.max(2 * self.kh)
    }

    /// The image rows `lo..hi` that output rows `y0..y1` read (`None` when they read none).
    fn source_range(&self, y0: usize, y1: usize) -> Option<(usize, usize)> {
        let sources = (y0..y1 + self.kh - 1).filter_map(|q| self.rows.source(q));
        let (lo, hi) = sources.fold((usize::MAX, 0), |(lo, hi), r| (lo.min(r), hi.max(r + 1)));
        (lo < hi).then_some((lo, hi))
    }

    /// The extremum of output rows `y0 .. y0 + out.len() / n` into `out`, reading image row `r`
    /// at `src[(r − src_row0)·n ..]` (rows `src` does not hold read as neutral).
    fn run_rows<M: Extremum, T: Sample>(
        &self,
        src: &[T],
        src_row0: usize,
        y0: usize,
        out: &mut [T],
        buffers: &mut BandBuffers<T>,
    ) {
        let n = self.n;
        let channels = self.channels;
        let padded_n = self.columns.padded_len() * channels;
        let neutral = M::neutral::<T>();
        let BandBuffers {
            padded,
            horizontal,
            scratch,
        } = buffers;
        let out_rows = out.len() / n;
        // Extended rows y0 .. y0 + out_rows + kh − 1, each padded through the column table.
        let extended = out_rows + self.kh - 1;
        padded.resize(extended * padded_n, neutral);
        horizontal.resize(extended * n, neutral);
        let padded = &mut padded[..extended * padded_n];
        for (q, line) in padded.chunks_exact_mut(padded_n).enumerate() {
            let row = self
                .rows
                .source(y0 + q)
                .and_then(|r| r.checked_sub(src_row0))
                .and_then(|r| src.get(r * n..(r + 1) * n));
            match row {
                Some(row) => self.columns.pad_row(row, channels, neutral, line),
                None => line.fill(neutral),
            }
        }
        for (index, &((first, len), j0, rows_in_group)) in self.groups.iter().enumerate() {
            let used = out_rows + rows_in_group - 1;
            let horizontal = &mut horizontal[..used * n];
            for (e, line) in horizontal.chunks_exact_mut(n).enumerate() {
                let start = (j0 + e) * padded_n + first * channels;
                if let Some(row) = padded.get(start..start + n + (len - 1) * channels) {
                    window_extremum::<M, T>(row, channels, len, line, false, scratch);
                }
            }
            if rows_in_group <= DIRECT_MAX_TAPS {
                // Row by row, so that the taps and the output row stay in L1.
                direct_rows::<M, T>(horizontal, n, rows_in_group, out, index > 0);
            } else {
                window_extremum::<M, T>(horizontal, n, rows_in_group, out, index > 0, scratch);
            }
        }
    }
}

/// The extremum under `element` of every sample of `src` (an image of `image`'s geometry),
/// in parallel bands of rows.
fn extremum_bands<M: Extremum, T: Sample>(
    image: &Image,
    src: &[T],
    element: &StructuringElement,
    border: MorphBorder,
) -> Vec<T> {
    let mut dst = ocellus_engine::buffer::zeroed::<T>(src.len());
    let (width, height) = (image.width(), image.height());
    let channels = image.channels().count();
    let n = width * channels;
    if n == 0 || height == 0 || src.len() != n * height {
        return dst;
    }
    let pass = Pass::new(width, height, channels, element, border);
    let band_rows = pass.band_rows();
    dst.par_chunks_mut(band_rows * n)
        .enumerate()
        // Buffers are reused across the bands a worker takes; every sample read is written
        // first in each band, so reuse cannot change results.
        .for_each_init(BandBuffers::default, |buffers, (band, out)| {
            pass.run_rows::<M, T>(src, 0, band * band_rows, out, buffers);
        });
    dst
}

/// `second(first(src))` with one element in one parallel sweep: each band computes the rows of
/// the first pass it needs into a band buffer and runs the second pass on them, so no
/// intermediate image is allocated. `None` when the first pass's rows a band needs are not a
/// short range (wrap borders), for the caller to run the passes one after the other.
fn fused_bands<A: Extremum, B: Extremum, T: Sample>(
    image: &Image,
    src: &[T],
    element: &StructuringElement,
    border: MorphBorder,
) -> Option<Vec<T>> {
    let (width, height) = (image.width(), image.height());
    let channels = image.channels().count();
    let n = width * channels;
    if n == 0 || height == 0 || src.len() != n * height {
        return None;
    }
    let pass = Pass::new(width, height, channels, element, border);
    let band_rows = pass.band_rows();
    // Every band must read a contiguous range of first-pass rows not much taller than itself.
    let bands = height.div_ceil(band_rows);
    let ranges: Vec<(usize, usize)> = (0..bands)
        .map(|b| {
            let y0 = b * band_rows;
            let y1 = (y0 + band_rows).min(height);
            pass.source_range(y0, y1).unwrap_or((y0, y0))
        })
        .collect();
    if ranges
        .iter()
        .any(|&(lo, hi)| hi - lo > band_rows + 2 * pass.kh)
    {
        return None;
    }
    let mut dst = ocellus_engine::buffer::zeroed::<T>(src.len());
    dst.par_chunks_mut(band_rows * n).enumerate().for_each_init(
        || (BandBuffers::default(), Vec::new()),
        |(buffers, stage), (band, out)| {
            let (lo, hi) = ranges[band];
            stage.resize((hi - lo) * n, T::default());
            pass.run_rows::<A, T>(src, 0, lo, &mut stage[..(hi - lo) * n], buffers);
            pass.run_rows::<B, T>(&stage[..(hi - lo) * n], lo, band * band_rows, out, buffers);
        },
    );
    Some(dst)
}

/// Per-worker buffers of one band: padded source rows, horizontal results, van Herk scratch.
struct BandBuffers<T> {
    padded: Vec<T>,
    horizontal: Vec<T>,
    scratch: Scratch<T>,
}

impl<T> Default for BandBuffers<T> {
    fn default() -> Self {
        BandBuffers {
            padded: Vec::new(),
            horizontal: Vec::new(),
            scratch: Scratch::default(),
        }
    }
}

/// Reusable buffers of the van Herk passes.
struct Scratch<T> {
    prefix: Vec<T>,
    suffix: Vec<T>,
}

impl<T> Default for Scratch<T> {
    fn default() -> Self {
        Scratch {
            prefix: Vec::new(),
            suffix: Vec::new(),
        }
    }
}

/// [`direct`] over each row of `out` (rows of `n` samples), reading rows `y .. y + len` of
/// `horizontal` for output row `y`: row by row, so that the taps and the output row stay in L1.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn direct_rows<M: Extremum, T: Sample>(
    horizontal: &[T],
    n: usize,
    len: usize,
    out: &mut [T],
    combine: bool,
) {
    for (y, line) in out.chunks_exact_mut(n).enumerate() {
        direct::<M, T>(&horizontal[y * n..], n, len, line, combine);
    }
}

/// `out[i] = op_{k < len} src[i + k·stride]` (combined with the old `out[i]` when `combine`).
/// `src` holds `out.len() + (len − 1)·stride` samples; `out.len()` is a multiple of `stride`.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn window_extremum<M: Extremum, T: Sample>(
    src: &[T],
    stride: usize,
    len: usize,
    out: &mut [T],
    combine: bool,
    scratch: &mut Scratch<T>,
) {
    let n = out.len();
    let span = n + len.saturating_sub(1) * stride;
    if len == 0 || stride == 0 || src.len() < span {
        return;
    }
    if len <= DIRECT_MAX_TAPS {
        direct::<M, T>(src, stride, len, out, combine);
    } else if stride < WIDE_STRIDE && len <= DOUBLING_MAX_TAPS {
        doubling::<M, T>(&src[..span], stride, len, out, combine, scratch);
    } else {
        van_herk::<M, T>(&src[..span], stride, len, out, combine, scratch);
    }
}

/// The extremum of `len` shifted slices, two taps per pass over `out` (vectorizes).
/// `src` holds at least `out.len() + (len − 1)·stride` samples.
#[inline(always)]
fn direct<M: Extremum, T: Sample>(
    src: &[T],
    stride: usize,
    len: usize,
    out: &mut [T],
    combine: bool,
) {
    let n = out.len();
    if len == 0 || src.len() < n + (len - 1) * stride {
        return;
    }
    let tap = |k: usize| &src[k * stride..k * stride + n];
    // Short windows in one pass over `out` (fewer loads and stores than pairs of taps).
    match (len, combine) {
        (3, false) => {
            for (((o, &a), &b), &c) in out.iter_mut().zip(tap(0)).zip(tap(1)).zip(tap(2)) {
                *o = M::pick(M::pick(a, b), c);
            }
            return;
        }
        (5, false) => {
            let taps = out
                .iter_mut()
                .zip(tap(0))
                .zip(tap(1))
                .zip(tap(2))
                .zip(tap(3))
                .zip(tap(4));
            for (((((o, &a), &b), &c), &d), &e) in taps {
                *o = M::pick(M::pick(M::pick(a, b), M::pick(c, d)), e);
            }
            return;
        }
        (5, true) => {
            let taps = out
                .iter_mut()
                .zip(tap(0))
                .zip(tap(1))
                .zip(tap(2))
                .zip(tap(3))
                .zip(tap(4));
            for (((((o, &a), &b), &c), &d), &e) in taps {
                // The pairing of the general loop below (same result for NaN too).
                *o = M::pick(M::pick(M::pick(*o, M::pick(a, b)), M::pick(c, d)), e);
            }
            return;
        }
        _ => {}
    }
    let mut k = 1;
    match (combine, len) {
        (false, 1) => out.copy_from_slice(tap(0)),
        (true, 1) => {
            for (o, &x) in out.iter_mut().zip(tap(0)) {
                *o = M::pick(*o, x);
            }
        }
        (false, _) => {
            for ((o, &a), &b) in out.iter_mut().zip(tap(0)).zip(tap(1)) {
                *o = M::pick(a, b);
            }
            k = 2;
        }
        (true, _) => {
            for ((o, &a), &b) in out.iter_mut().zip(tap(0)).zip(tap(1)) {
                *o = M::pick(*o, M::pick(a, b));
            }
            k = 2;
        }
    }
    while k + 1 < len {
        for ((o, &a), &b) in out.iter_mut().zip(tap(k)).zip(tap(k + 1)) {
            *o = M::pick(*o, M::pick(a, b));
        }
        k += 2;
    }
    if k < len {
        for (o, &a) in out.iter_mut().zip(tap(k)) {
            *o = M::pick(*o, a);
        }
    }
}

/// The extremum over windows of `len` by doubling: windows of 2, 4, … p samples (p the largest
/// power of two ≤ `len`) each from two of the previous ones, then
/// `out[i] = op(w_p[i], w_p[i + (len − p)·stride])`. ⌈log₂ len⌉ vectorized passes, which along
/// rows of few channels beats the scalar van Herk recurrences for moderate lengths.
#[inline(always)]
fn doubling<M: Extremum, T: Sample>(
    src: &[T],
    stride: usize,
    len: usize,
    out: &mut [T],
    combine: bool,
    scratch: &mut Scratch<T>,
) {
    let Scratch {
        prefix: a,
        suffix: b,
    } = scratch;
    a.clear();
    a.extend_from_slice(src);
    let mut window = 1;
    while window * 2 <= len {
        let d = window * stride;
        let valid = a.len() - d;
        b.clear();
        b.extend(a[..valid].iter().zip(&a[d..]).map(|(&x, &y)| M::pick(x, y)));
        std::mem::swap(a, b);
        window *= 2;
    }
    let rest = (len - window) * stride;
    let n = out.len();
    if a.len() < n + rest {
        return;
    }
    let (head, tail) = (&a[..n], &a[rest..rest + n]);
    if combine {
        for ((o, &x), &y) in out.iter_mut().zip(head).zip(tail) {
            *o = M::pick(*o, M::pick(x, y));
        }
    } else {
        for ((o, &x), &y) in out.iter_mut().zip(head).zip(tail) {
            *o = M::pick(x, y);
        }
    }
}

/// van Herk / Gil-Werman: running extrema within blocks of `len` positions from both ends, then
/// one comparison per output. `src` holds exactly `out.len() + (len − 1)·stride` samples.
#[inline(always)]
fn van_herk<M: Extremum, T: Sample>(
    src: &[T],
    stride: usize,
    len: usize,
    out: &mut [T],
    combine: bool,
    scratch: &mut Scratch<T>,
) {
    let span = src.len();
    let Scratch { prefix, suffix } = scratch;
    prefix.clear();
    prefix.extend_from_slice(src);
    suffix.clear();
    suffix.extend_from_slice(src);
    let block = len * stride;
    for b in (0..span).step_by(block) {
        let end = (b + block).min(span);
        if stride < WIDE_STRIDE {
            // Interleaved pixels along a row: one scalar recurrence per channel, the running
            // value kept in a register (through memory, each step would wait on the store).
            for channel in b..b + stride {
                let mut acc = src[channel];
                for i in (channel + stride..end).step_by(stride) {
                    acc = M::pick(acc, src[i]);
                    prefix[i] = acc;
                }
                let last = end - stride + (channel - b);
                let mut acc = src[last];
                for i in (channel..last).step_by(stride).rev() {
                    acc = M::pick(src[i], acc);
                    suffix[i] = acc;
                }
            }
            continue;
        }
        // Whole rows: element-wise over slices, which vectorizes.
        // Prefix: position k of the block takes the extremum of positions 0..=k.
        for line in (b + stride..end).step_by(stride) {
            let (done, rest) = prefix.split_at_mut(line);
            let previous = &done[line - stride..];
            for (p, &q) in rest[..stride].iter_mut().zip(previous) {
                *p = M::pick(q, *p);
            }
        }
        // Suffix: position k takes the extremum of positions k..len.
        for line in (b..end.saturating_sub(stride)).step_by(stride).rev() {
            let (head, next) = suffix.split_at_mut(line + stride);
            for (s, &q) in head[line..].iter_mut().zip(&next[..stride]) {
                *s = M::pick(*s, q);
            }
        }
    }
    let reach = (len - 1) * stride;
    let ends = &prefix[reach..];
    if combine {
        for ((o, &s), &p) in out.iter_mut().zip(suffix.iter()).zip(ends) {
            *o = M::pick(*o, M::pick(s, p));
        }
    } else {
        for ((o, &s), &p) in out.iter_mut().zip(suffix.iter()).zip(ends) {
            *o = M::pick(s, p);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::border::map_index;
    use crate::filter::test_support::randoms;
    use ocellus_engine::value::Channels;
    use proptest::prelude::*;

    #[derive(Debug, Clone, Copy, PartialEq)]
    enum Kind {
        U8,
        U16,
        F32,
    }

    fn random_image(w: usize, h: usize, channels: Channels, kind: Kind, seed: u64) -> Image {
        let r = randoms(seed, w * h * channels.count());
        match kind {
            Kind::U8 => Image::from_u8(
                w,
                h,
                channels,
                r.iter().map(|x| (x * 256.0) as u8).collect(),
            ),
            Kind::U16 => Image::from_u16(
                w,
                h,
                channels,
                r.iter().map(|x| (x * 65536.0) as u16).collect(),
            ),
            Kind::F32 => Image::from_f32(
                w,
                h,
                channels,
                r.iter().map(|x| (*x as f32) * 2.0 - 0.5).collect(),
            ),
        }
        .unwrap()
    }

    fn samples(image: &Image) -> Vec<f64> {
        match image.data() {
            PixelData::U8(v) => v.iter().map(|&x| f64::from(x)).collect(),
            PixelData::U16(v) => v.iter().map(|&x| f64::from(x)).collect(),
            PixelData::F32(v) => v.iter().map(|&x| f64::from(x)).collect(),
        }
    }

    /// Direct minimum or maximum over the element's cells through `map_index`: the definition.
    fn reference(
        image: &Image,
        element: &StructuringElement,
        border: MorphBorder,
        erosion: bool,
    ) -> Vec<f64> {
        let (w, h, c) = (image.width(), image.height(), image.channels().count());
        let src = samples(image);
        let (ax, ay) = element.anchor();
        let mode = border.border_mode();
        // The neutral value in the image's own range (cells off the image all read it).
        let high = match image.data() {
            PixelData::U8(_) => 255.0,
            PixelData::U16(_) => 65535.0,
            PixelData::F32(_) => f64::INFINITY,
        };
        let neutral = if erosion {
            high
        } else if high.is_finite() {
            0.0
        } else {
            f64::NEG_INFINITY
        };
        let mut out = vec![0.0; src.len()];
        for y in 0..h {
            for x in 0..w {
                for ch in 0..c {
                    let mut acc = neutral;
                    for j in 0..element.height() {
                        for i in 0..element.width() {
                            if !element.contains(i, j) {
                                continue;
                            }
                            let sx = map_index(x as isize + i as isize - ax as isize, w, mode);
                            let sy = map_index(y as isize + j as isize - ay as isize, h, mode);
                            let v = match (sx, sy) {
                                (Some(sx), Some(sy)) => src[(sy * w + sx) * c + ch],
                                _ => neutral,
                            };
                            acc = if erosion { acc.min(v) } else { acc.max(v) };
                        }
                    }
                    out[(y * w + x) * c + ch] = acc;
                }
            }
        }
        out
    }

    fn element(shape: Shape, w: usize, h: usize) -> StructuringElement {
        StructuringElement::new(shape, w, h).unwrap()
    }

    fn gray_u8(w: usize, h: usize, data: Vec<u8>) -> Image {
        Image::from_u8(w, h, Channels::Gray, data).unwrap()
    }

    #[test]
    fn five_by_five_by_hand() {
        let img = gray_u8(5, 5, (1..=25).collect());
        let rect = element(Shape::Rect, 3, 3);
        #[rustfmt::skip]
        let eroded: Vec<u8> = vec![
             1,  1,  2,  3,  4,
             1,  1,  2,  3,  4,
             6,  6,  7,  8,  9,
            11, 11, 12, 13, 14,
            16, 16, 17, 18, 19,
        ];
        #[rustfmt::skip]
        let dilated: Vec<u8> = vec![
             7,  8,  9, 10, 10,
            12, 13, 14, 15, 15,
            17, 18, 19, 20, 20,
            22, 23, 24, 25, 25,
            22, 23, 24, 25, 25,
        ];
        let e = erode(&img, &rect, 1, MorphBorder::Neutral);
        assert_eq!(e.as_u8().unwrap(), &eroded[..]);
        let d = dilate(&img, &rect, 1, MorphBorder::Neutral);
        assert_eq!(d.as_u8().unwrap(), &dilated[..]);
        // A single bright pixel dilated by a cross becomes a plus sign.
        let mut dot = vec![0u8; 25];
        dot[12] = 9;
        let plus = dilate(
            &gray_u8(5, 5, dot),
            &element(Shape::Cross, 3, 3),
            1,
            MorphBorder::Neutral,
        );
        #[rustfmt::skip]
        let expected: Vec<u8> = vec![
            0, 0, 0, 0, 0,
            0, 0, 9, 0, 0,
            0, 9, 9, 9, 0,
            0, 0, 9, 0, 0,
            0, 0, 0, 0, 0,
        ];
        assert_eq!(plus.as_u8().unwrap(), &expected[..]);
    }

    #[test]
    fn elements_match_opencv() {
        let cells = |e: &StructuringElement| -> Vec<String> {
            (0..e.height())
                .map(|y| {
                    (0..e.width())
                        .map(|x| if e.contains(x, y) { '1' } else { '0' })
                        .collect()
                })
                .collect()
        };
        // cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5)) and (7, 5).
        assert_eq!(
            cells(&element(Shape::Ellipse, 5, 5)),
            ["00100", "11111", "11111", "11111", "00100"]
        );
        assert_eq!(
            cells(&element(Shape::Ellipse, 7, 5)),
            ["0001000", "1111111", "1111111", "1111111", "0001000"]
        );
        // The rest of cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (w, h)), OpenCV 5.0.
        let opencv: [((usize, usize), &[&str]); 7] = [
            ((4, 6), &["0010", "0111", "1111", "1111", "1111", "0111"]),
            ((6, 4), &["000100", "111111", "111111", "111111"]),
            (
                (9, 9),
                &[
                    "000010000",
                    "011111110",
                    "011111110",
                    "111111111",
                    "111111111",
                    "111111111",
                    "011111110",
                    "011111110",
                    "000010000",
                ],
            ),
            ((2, 3), &["01", "11", "01"]),
            (
                (15, 15),
                &[
                    "000000010000000",
                    "000111111111000",
                    "001111111111100",
                    "011111111111110",
                    "011111111111110",
                    "111111111111111",
                    "111111111111111",
                    "111111111111111",
                    "111111111111111",
                    "111111111111111",
                    "011111111111110",
                    "011111111111110",
                    "001111111111100",
                    "000111111111000",
                    "000000010000000",
                ],
            ),
            ((1, 5), &["1", "1", "1", "1", "1"]),
            ((5, 1), &["00100"]),
        ];
        for ((w, h), expected) in opencv {
            assert_eq!(cells(&element(Shape::Ellipse, w, h)), expected, "{w}×{h}");
        }
        assert_eq!(cells(&element(Shape::Cross, 3, 2)), ["010", "111"]);
        assert_eq!(element(Shape::Rect, 4, 2).anchor(), (2, 1));
        assert!(StructuringElement::new(Shape::Rect, 0, 3).is_none());
        // Groups: a cross is two rectangles, an ellipse one per distinct row width.
        assert_eq!(element(Shape::Rect, 5, 5).groups().len(), 1);
        assert_eq!(element(Shape::Cross, 5, 5).groups().len(), 2);
        assert_eq!(element(Shape::Ellipse, 5, 5).groups().len(), 2);
    }

    #[test]
    fn custom_elements() {
        let e = StructuringElement::from_mask(&[vec![1, 0, 1], vec![0, 1]], None).unwrap();
        assert_eq!((e.width(), e.height(), e.anchor()), (3, 2, (1, 1)));
        assert_eq!(e.offsets(), [(-1, -1), (1, -1), (0, 0)]);
        assert!(!e.contains(2, 1));
        // Two runs in the first row: three groups at most, one cell each or merged.
        assert!(!e.groups().is_empty());
        assert!(StructuringElement::from_mask(&[], None).is_err());
        assert!(StructuringElement::from_mask(&[vec![0, 0]], None).is_err());
        assert!(StructuringElement::from_mask(&[vec![1]], Some((1, 0))).is_err());
        let r = e.reflected();
        assert_eq!(r.anchor(), (1, 0));
        assert!(r.contains(1, 0) && r.contains(0, 1) && r.contains(2, 1) && !r.contains(0, 0));
        // Hand case: erosion by a horizontal pair [1, 1] anchored at its left cell.
        let img = gray_u8(4, 1, vec![5, 3, 9, 7]);
        let pair = StructuringElement::from_mask(&[vec![1, 1]], Some((0, 0))).unwrap();
        assert_eq!(
            erode(&img, &pair, 1, MorphBorder::Neutral).as_u8().unwrap(),
            [3, 3, 7, 7]
        );
        let p = |element: Vec<Vec<u8>>, anchor| {
            Morphology::new(MorphologyParams {
                element,
                anchor,
                ..MorphologyParams::default()
            })
        };
        assert!(p(vec![vec![1, 1]], Some([1, 0])).is_ok());
        let err = p(vec![vec![0]], None).unwrap_err();
        assert!(err.contains("element"), "{err}");
        let err = p(vec![], Some([3, 3])).unwrap_err();
        assert!(err.contains("anchor"), "{err}");
    }

    const BORDERS: [MorphBorder; 5] = [
        MorphBorder::Neutral,
        MorphBorder::Clamp,
        MorphBorder::Reflect,
        MorphBorder::Reflect101,
        MorphBorder::Wrap,
    ];

    #[test]
    fn large_elements_match_the_definition() {
        // Sizes past DIRECT_MAX_TAPS go through van Herk in both directions.
        for (k, (w, h)) in [(9, (23, 17)), (12, (30, 9)), (17, (20, 41)), (31, (12, 13))] {
            for shape in Shape::ALL {
                for border in BORDERS {
                    for kind in [Kind::U8, Kind::F32] {
                        let img = random_image(w, h, Channels::Rgb, kind, k as u64);
                        let e = element(*shape, k, k + 2);
                        assert_eq!(
                            samples(&erode(&img, &e, 1, border)),
                            reference(&img, &e, border, true),
                            "erode {shape:?} {k} {border:?} {kind:?}"
                        );
                        assert_eq!(
                            samples(&dilate(&img, &e, 1, border)),
                            reference(&img, &e, border, false),
                            "dilate {shape:?} {k} {border:?} {kind:?}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn van_herk_equals_direct_windows() {
        let src: Vec<u16> = randoms(7, 500)
            .iter()
            .map(|r| (r * 1000.0) as u16)
            .collect();
        for stride in 1..5 {
            for len in 1..70 {
                let n = ((src.len() - (len - 1) * stride) / stride) * stride;
                let mut a = vec![0; n];
                let mut b = vec![0; n];
                let span = n + (len - 1) * stride;
                van_herk::<Min, u16>(
                    &src[..span],
                    stride,
                    len,
                    &mut a,
                    false,
                    &mut Scratch::default(),
                );
                direct::<Min, u16>(&src, stride, len, &mut b, false);
                assert_eq!(a, b, "stride {stride} len {len}");
                let mut c = vec![0; n];
                doubling::<Min, u16>(
                    &src[..span],
                    stride,
                    len,
                    &mut c,
                    false,
                    &mut Scratch::default(),
                );
                assert_eq!(c, b, "doubling stride {stride} len {len}");
            }
        }
    }

    #[test]
    fn duality_for_u8() {
        for border in BORDERS {
            for shape in Shape::ALL {
                let img = random_image(19, 13, Channels::Rgba, Kind::U8, 11);
                let inverted =
                    |i: &Image| gray_like(i, i.as_u8().unwrap().iter().map(|&x| 255 - x).collect());
                let e = element(*shape, 5, 3);
                assert_eq!(
                    erode(&img, &e, 1, border),
                    inverted(&dilate(&inverted(&img), &e, 1, border))
                );
            }
        }
    }

    fn gray_like(image: &Image, data: Vec<u8>) -> Image {
        Image::from_u8(image.width(), image.height(), image.channels(), data).unwrap()
    }

    #[test]
    fn opening_and_closing_laws() {
        for shape in Shape::ALL {
            for k in [1, 3, 5, 7] {
                let img = random_image(23, 19, Channels::Gray, Kind::U8, k as u64);
                let e = element(*shape, k, k);
                let border = MorphBorder::Neutral;
                let open = morphology(&img, Operation::Open, &e, 1, border);
                let close = morphology(&img, Operation::Close, &e, 1, border);
                assert_eq!(morphology(&open, Operation::Open, &e, 1, border), open);
                assert_eq!(morphology(&close, Operation::Close, &e, 1, border), close);
                let (s, o, c) = (samples(&img), samples(&open), samples(&close));
                assert!(o.iter().zip(&s).all(|(o, s)| o <= s), "open ≤ I");
                assert!(c.iter().zip(&s).all(|(c, s)| c >= s), "I ≤ close");
            }
        }
    }

    #[test]
    fn compound_operations_are_differences() {
        let img = random_image(17, 11, Channels::Rgb, Kind::F32, 3);
        for shape in Shape::ALL {
            for border in BORDERS {
                let e = element(*shape, 4, 3);
                let gradient = morphology(&img, Operation::Gradient, &e, 1, border);
                assert!(samples(&gradient).iter().all(|&g| g >= 0.0));
                let open = samples(&morphology(&img, Operation::Open, &e, 1, border));
                let tophat = samples(&morphology(&img, Operation::Tophat, &e, 1, border));
                let s = samples(&img);
                for i in 0..s.len() {
                    assert_eq!(tophat[i], f64::from((s[i] - open[i]) as f32));
                }
            }
        }
        // Unsigned differences saturate instead of wrapping.
        let img = random_image(9, 7, Channels::Gray, Kind::U16, 4);
        let e = element(Shape::Rect, 3, 3);
        let blackhat = morphology(&img, Operation::Blackhat, &e, 1, MorphBorder::Reflect);
        let close = samples(&morphology(
            &img,
            Operation::Close,
            &e,
            1,
            MorphBorder::Reflect,
        ));
        let expected: Vec<f64> = close
            .iter()
            .zip(samples(&img))
            .map(|(c, s)| (c - s).max(0.0))
            .collect();
        assert_eq!(samples(&blackhat), expected);
    }

    #[test]
    fn iterations() {
        let img = random_image(31, 29, Channels::Gray, Kind::U8, 9);
        let three = element(Shape::Rect, 3, 3);
        let five = element(Shape::Rect, 5, 5);
        let n = MorphBorder::Neutral;
        let twice = erode(&img, &three, 2, n);
        assert_eq!(twice, erode(&img, &five, 1, n));
        assert_eq!(twice, erode(&erode(&img, &three, 1, n), &three, 1, n));
        // Non-full elements are applied repeatedly.
        let cross = element(Shape::Cross, 3, 3);
        for border in BORDERS {
            assert_eq!(
                dilate(&img, &cross, 3, border),
                dilate(
                    &dilate(&dilate(&img, &cross, 1, border), &cross, 1, border),
                    &cross,
                    1,
                    border
                )
            );
        }
    }

    #[test]
    fn identity_tiny_and_empty_images() {
        let img = random_image(7, 5, Channels::Rgb, Kind::U16, 1);
        let one = element(Shape::Rect, 1, 1);
        for border in BORDERS {
            assert_eq!(erode(&img, &one, 3, border), img);
            assert_eq!(dilate(&img, &one, 1, border), img);
        }
        for (w, h) in [(0, 5), (5, 0), (0, 0)] {
            let empty = Image::from_f32(w, h, Channels::Gray, vec![]).unwrap();
            let e = element(Shape::Ellipse, 5, 5);
            assert_eq!(erode(&empty, &e, 1, MorphBorder::Reflect), empty);
            assert_eq!(
                morphology(&empty, Operation::Gradient, &e, 2, MorphBorder::Neutral),
                empty
            );
        }
        let single = gray_u8(1, 1, vec![42]);
        for shape in Shape::ALL {
            for border in BORDERS {
                let e = element(*shape, 6, 5);
                assert_eq!(erode(&single, &e, 1, border), single);
                assert_eq!(dilate(&single, &e, 2, border), single);
            }
        }
    }

    #[test]
    fn output_is_identical_for_any_thread_count() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let img = random_image(301, 257, Channels::Rgb, Kind::U8, 5);
        for (shape, k) in [(Shape::Rect, 5), (Shape::Ellipse, 11), (Shape::Cross, 15)] {
            let e = element(shape, k, k);
            let run = || morphology(&img, Operation::Gradient, &e, 2, MorphBorder::Reflect101);
            assert_eq!(pool(1).install(run), pool(3).install(run));
        }
    }

    #[test]
    fn operator_params_are_checked() {
        let p = |f: fn(&mut MorphologyParams)| {
            let mut p = MorphologyParams::default();
            f(&mut p);
            Morphology::new(p)
        };
        assert!(p(|_| ()).is_ok());
        let e = p(|p| p.ksize = [0, 3]).unwrap_err();
        assert!(e.contains("width"), "{e}");
        let e = p(|p| p.ksize = [3, 1024]).unwrap_err();
        assert!(e.contains("height"), "{e}");
        let e = p(|p| p.iterations = 0).unwrap_err();
        assert!(e.contains("iterations"), "{e}");
        assert!(
            Erode::new(MorphParams {
                iterations: 256,
                ..MorphParams::default()
            })
            .is_err()
        );
        assert!(
            Dilate::new(MorphParams {
                ksize: [1, 1],
                ..MorphParams::default()
            })
            .is_ok()
        );
    }

    #[test]
    fn operators_run() {
        let img = random_image(20, 10, Channels::Rgb, Kind::U8, 3);
        let specs = Erode::inputs();
        let values = [Some(Value::image(img.clone()))];
        let ctx = RunContext {
            node: "m".into(),
            threads: 1,
            element: None,
        };
        let rect = element(Shape::Rect, 3, 3);
        let run = |op: &dyn Operator| {
            let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
            match out.take("image") {
                Some(Value::Image(got)) => (*got).clone(),
                _ => panic!("expected an image"),
            }
        };
        let n = MorphBorder::Neutral;
        assert_eq!(
            run(&Erode::new(MorphParams::default()).unwrap()),
            erode(&img, &rect, 1, n)
        );
        assert_eq!(
            run(&Dilate::new(MorphParams::default()).unwrap()),
            dilate(&img, &rect, 1, n)
        );
        assert_eq!(
            run(&Morphology::new(MorphologyParams::default()).unwrap()),
            morphology(&img, Operation::Open, &rect, 1, n)
        );
        let op = Erode::new(MorphParams::default()).unwrap();
        let err = op.run(&ctx, &Inputs::new(&specs, &[None])).unwrap_err();
        assert!(err.to_string().contains("not connected"));
        let err = op
            .run(&ctx, &Inputs::new(&specs, &[Some(Value::Scalar(1.0))]))
            .unwrap_err();
        assert!(err.to_string().contains("expected Image"), "{err}");
    }

    fn any_border() -> impl Strategy<Value = MorphBorder> {
        prop::sample::select(BORDERS.to_vec())
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]

        #[test]
        fn matches_the_definition(
            w in 1usize..12,
            h in 1usize..12,
            kw in 1usize..8,
            kh in 1usize..8,
            shape in prop::sample::select(Shape::ALL.to_vec()),
            border in any_border(),
            kind in prop::sample::select(vec![Kind::U8, Kind::U16, Kind::F32]),
            channels in prop::sample::select(vec![Channels::Gray, Channels::Rgb, Channels::Rgba]),
            erosion in any::<bool>(),
            seed in any::<u64>(),
        ) {
            let img = random_image(w, h, channels, kind, seed);
            let e = element(shape, kw, kh);
            let got = if erosion { erode(&img, &e, 1, border) } else { dilate(&img, &e, 1, border) };
            prop_assert_eq!(got.format(), img.format());
            prop_assert_eq!(samples(&got), reference(&img, &e, border, erosion));
        }

        #[test]
        fn any_element_matches_the_definition(
            w in 1usize..14,
            h in 1usize..14,
            mask in prop::collection::vec(prop::collection::vec(0u8..2, 1..7), 1..7),
            ax in 0usize..7,
            ay in 0usize..7,
            border in any_border(),
            kind in prop::sample::select(vec![Kind::U8, Kind::F32]),
            erosion in any::<bool>(),
            seed in any::<u64>(),
        ) {
            let img = random_image(w, h, Channels::Rgb, kind, seed);
            let Ok(e) = StructuringElement::from_mask(&mask, Some((ax, ay))) else {
                return Ok(());
            };
            let got = if erosion { erode(&img, &e, 1, border) } else { dilate(&img, &e, 1, border) };
            prop_assert_eq!(samples(&got), reference(&img, &e, border, erosion));
            // Iterated custom elements are repeated passes. A full (rectangular) element is
            // instead grown to (k − 1)·n + 1 as OpenCV does, which differs at reflected borders.
            if e.is_full() {
                return Ok(());
            }
            let twice = if erosion { erode(&img, &e, 2, border) } else { dilate(&img, &e, 2, border) };
            let again = if erosion { erode(&got, &e, 1, border) } else { dilate(&got, &e, 1, border) };
            prop_assert_eq!(twice, again);
        }

        #[test]
        fn fused_open_and_close_equal_two_passes(
            w in 1usize..40,
            h in 1usize..90,
            k in 1usize..12,
            shape in prop::sample::select(Shape::ALL.to_vec()),
            border in any_border(),
            iterations in 1usize..3,
            seed in any::<u64>(),
        ) {
            let img = random_image(w, h, Channels::Gray, Kind::U8, seed);
            let e = element(shape, k, k / 2 + 1);
            prop_assert_eq!(
                morphology(&img, Operation::Open, &e, iterations, border),
                dilate(&erode(&img, &e, iterations, border), &e, iterations, border)
            );
            prop_assert_eq!(
                morphology(&img, Operation::Close, &e, iterations, border),
                erode(&dilate(&img, &e, iterations, border), &e, iterations, border)
            );
        }
    }
}
