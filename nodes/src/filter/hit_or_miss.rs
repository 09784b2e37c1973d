//! Binary morphology: `filter.hit_or_miss`, `filter.thinning`, `filter.thickening` and
//! `filter.skeleton`.
//!
//! Inputs are single-channel u8 images read as binary (nonzero = foreground); outputs are 0/255.
//!
//! - Hit-or-miss with a three-valued element (1 = must be foreground, −1 = must be background,
//!   0 = ignored) is `erode(A, fg) ∧ erode(¬A, bg)`, OpenCV's `MORPH_HITMISS`; both erosions
//!   run through [`super::morphology::erode`] with OpenCV's neutral border (pixels outside the
//!   image satisfy every condition).
//! - Thinning "golay" removes, in turn, the hits of the eight rotated Golay L elements
//!   (Gonzalez & Woods, *Digital Image Processing*, thinning `A ⊗ B = A − (A ⊛ B)`), until a
//!   whole round of eight changes nothing. Each 3×3 hit-or-miss is a table lookup of the
//!   pixel's 8-neighbour code; pixels outside the image are background.
//! - Thinning "zhang_suen" is the two-sub-iteration algorithm of Zhang & Suen (1984) as in
//!   OpenCV's `ximgproc::thinning(THINNING_ZHANGSUEN)`: the one-pixel frame of the image is
//!   never changed.
//! - Thickening is the complement of the thinning of the complement.
//! - The skeleton is Lantuéjoul's formula `S = ∪ₖ Sₖ`, `Sₖ = (A ⊖ kB) − (A ⊖ kB) ∘ B`, with set
//!   erosion `A ⊖ B = {x : x + B ⊆ A}`, dilation `A ⊕ B = {a + b}` and opening
//!   `A ∘ B = (A ⊖ B) ⊕ B`; pixels outside the image are background, so every image erodes to
//!   nothing and the loop ends. `A = ∪ₖ Sₖ ⊕ kB`.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Value};
use ocellus_engine::{param_enum, params};

use super::morphology::{MorphBorder, Shape, StructuringElement, dilate, erode};

/// Largest hit-or-miss or skeleton element side, px.
pub const MAX_ELEMENT: usize = 255;

/// Largest `max_iterations`.
pub const MAX_ROUNDS: u32 = 1 << 20;

/// A binary image: `bits[y·width + x]` is 1 for foreground, 0 for background.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Binary {
    /// Width, px.
    pub width: usize,
    /// Height, px.
    pub height: usize,
    /// 0 or 1 per pixel, row-major.
    pub bits: Vec<u8>,
}

impl Binary {
    /// The binary image of a gray u8 image (nonzero = foreground), or an error naming the
    /// problem for other formats.
    pub fn from_image(image: &Image) -> Result<Binary, String> {
        match (image.channels(), image.data()) {
            (Channels::Gray, PixelData::U8(data)) => Ok(Binary {
                width: image.width(),
                height: image.height(),
                bits: data.iter().map(|&v| u8::from(v != 0)).collect(),
            }),
            _ => Err(format!(
                "expected a binary gray u8 image (nonzero = foreground), got {} {}",
                image.channels().name(),
                image.depth().name()
            )),
        }
    }

    /// The image: 255 for foreground, 0 for background.
    pub fn to_image(&self) -> Result<Image, String> {
        let data = self
            .bits
            .iter()
            .map(|&b| if b != 0 { 255 } else { 0 })
            .collect();
        Image::from_u8(self.width, self.height, Channels::Gray, data).map_err(|e| e.to_string())
    }

    /// Foreground ↔ background.
    pub fn complement(&self) -> Binary {
        Binary {
            bits: self.bits.iter().map(|&b| 1 - b.min(1)).collect(),
            ..self.clone()
        }
    }

    fn from_mask_image(image: &Image) -> Binary {
        Binary {
            width: image.width(),
            height: image.height(),
            bits: image
                .as_u8()
                .map(|d| d.iter().map(|&v| u8::from(v != 0)).collect())
                .unwrap_or_default(),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Hit-or-miss

/// A three-valued hit-or-miss element: the foreground cells, the background cells, the anchor.
#[derive(Debug, Clone, PartialEq)]
pub struct HitMissElement {
    width: usize,
    height: usize,
    cells: Vec<i8>,
    anchor: (usize, usize),
}

impl HitMissElement {
    /// From rows of 1 (foreground), −1 (background) and 0 (ignored), shorter rows padded with
    /// 0, anchored at `anchor` or the centre `(⌊w/2⌋, ⌊h/2⌋)`.
    pub fn new(
        rows: &[Vec<i32>],
        anchor: Option<(usize, usize)>,
    ) -> Result<HitMissElement, String> {
        let height = rows.len();
        let width = rows.iter().map(Vec::len).max().unwrap_or(0);
        if width == 0 || height == 0 {
            return Err("the element is empty".into());
        }
        if width > MAX_ELEMENT || height > MAX_ELEMENT {
            return Err(format!(
                "the element is {width}×{height}; each side must be at most {MAX_ELEMENT}"
            ));
        }
        let mut cells = vec![0i8; width * height];
        for (y, row) in rows.iter().enumerate() {
            for (x, &v) in row.iter().enumerate() {
                cells[y * width + x] = match v {
                    -1..=1 => v as i8,
                    _ => {
                        return Err(format!(
                            "element cell ({x}, {y}) is {v}; cells must be 1 (foreground), −1 (background) or 0 (ignored)"
                        ));
                    }
                };
            }
        }
        let anchor = anchor.unwrap_or((width / 2, height / 2));
        if anchor.0 >= width || anchor.1 >= height {
            return Err(format!(
                "anchor ({}, {}) lies outside the {width}×{height} element",
                anchor.0, anchor.1
            ));
        }
        Ok(HitMissElement {
            width,
            height,
            cells,
            anchor,
        })
    }

    /// The structuring element of the cells equal to `value`, `None` when there are none.
    fn part(&self, value: i8) -> Option<StructuringElement> {
        let mask: Vec<Vec<u8>> = self
            .cells
            .chunks(self.width)
            .map(|row| row.iter().map(|&c| u8::from(c == value)).collect())
            .collect();
        StructuringElement::from_mask(&mask, Some(self.anchor)).ok()
    }
}

/// Hit-or-miss transform of `a` by `element` (OpenCV's `MORPH_HITMISS`): 1 where every
/// foreground cell lies on foreground and every background cell on background; cells off the
/// image satisfy their condition. An element without foreground or background cells leaves
/// that condition always true.
pub fn hit_or_miss(a: &Binary, element: &HitMissElement) -> Result<Binary, String> {
    let image = a.to_image()?;
    let fit = |img: &Image, part: Option<StructuringElement>| match part {
        Some(e) => Binary::from_mask_image(&erode(img, &e, 1, MorphBorder::Neutral)),
        None => Binary {
            bits: vec![1; a.bits.len()],
            ..a.clone()
        },
    };
    let hits = fit(&image, element.part(1));
    let misses = fit(&a.complement().to_image()?, element.part(-1));
    Ok(Binary {
        bits: hits
            .bits
            .iter()
            .zip(&misses.bits)
            .map(|(&h, &m)| h & m)
            .collect(),
        ..a.clone()
    })
}

// ---------------------------------------------------------------------------------------------
// Thinning

param_enum! {
    /// Thinning algorithms.
    pub enum ThinningMethod {
        /// Sequential thinning by the eight rotated Golay L elements (Gonzalez & Woods).
        Golay = "golay",
        /// Zhang & Suen's two-sub-iteration thinning (OpenCV `ximgproc::thinning`).
        ZhangSuen = "zhang_suen",
    }
}

/// Ring positions of the 8 neighbours, clockwise from the top-left: `(dx, dy)`; bit `i` of a
/// neighbour code is the pixel at ring position `i`.
const RING: [(isize, isize); 8] = [
    (-1, -1),
    (0, -1),
    (1, -1),
    (1, 0),
    (1, 1),
    (0, 1),
    (-1, 1),
    (-1, 0),
];

/// The eight Golay L elements as `(foreground bits, background bits)` of the neighbour code
/// (the centre is foreground in all): L1 has its top row background and bottom row
/// foreground; each next one is the previous rotated clockwise by 45°.
pub fn golay_elements() -> [(u8, u8); 8] {
    // Top-left, top, top-right background; bottom-right, bottom, bottom-left foreground.
    let (mut fg, mut bg) = (0b0111_0000u8, 0b0000_0111u8);
    let mut out = [(0, 0); 8];
    for slot in &mut out {
        *slot = (fg, bg);
        fg = fg.rotate_left(1);
        bg = bg.rotate_left(1);
    }
    out
}

/// Lookup tables over the 256 neighbour codes.
fn golay_tables() -> [[bool; 256]; 8] {
    let mut tables = [[false; 256]; 8];
    for (table, (fg, bg)) in tables.iter_mut().zip(golay_elements()) {
        for (code, hit) in table.iter_mut().enumerate() {
            let code = code as u8;
            *hit = code & fg == fg && code & bg == 0;
        }
    }
    tables
}

/// Zhang–Suen removal tables for the two sub-iterations.
fn zhang_suen_tables() -> [[bool; 256]; 2] {
    let mut tables = [[false; 256]; 2];
    #[allow(clippy::needless_range_loop)] // `code` is the neighbour code, not just an index.
    for code in 0..256usize {
        let p = |i: usize| (code >> i) & 1;
        // Zhang & Suen's P2..P9 are the ring from the top, clockwise.
        let (p2, p3, p4, p5, p6, p7, p8, p9) = (p(1), p(2), p(3), p(4), p(5), p(6), p(7), p(0));
        let ring = [p2, p3, p4, p5, p6, p7, p8, p9];
        let transitions = (0..8)
            .filter(|&i| ring[i] == 0 && ring[(i + 1) % 8] == 1)
            .count();
        let count: usize = ring.iter().sum();
        let base = transitions == 1 && (2..=6).contains(&count);
        tables[0][code] = base && p2 * p4 * p6 == 0 && p4 * p6 * p8 == 0;
        tables[1][code] = base && p2 * p4 * p8 == 0 && p2 * p6 * p8 == 0;
    }
    tables
}

/// A binary image with a frame of one background pixel, for neighbour codes without bounds
/// checks.
struct Framed {
    pw: usize,
    ph: usize,
    bits: Vec<u8>,
}

impl Framed {
    fn new(a: &Binary) -> Framed {
        let (pw, ph) = (a.width + 2, a.height + 2);
        let mut bits = vec![0u8; pw * ph];
        for (y, row) in a.bits.chunks_exact(a.width.max(1)).enumerate() {
            bits[(y + 1) * pw + 1..(y + 1) * pw + 1 + a.width].copy_from_slice(row);
        }
        Framed { pw, ph, bits }
    }

    fn unframe(&self, width: usize, height: usize) -> Binary {
        let mut bits = Vec::with_capacity(width * height);
        for y in 0..height {
            bits.extend_from_slice(
                &self.bits[(y + 1) * self.pw + 1..(y + 1) * self.pw + 1 + width],
            );
        }
        Binary {
            width,
            height,
            bits,
        }
    }

    /// Removes, all at once, every foreground pixel in rows `y0..y1` and columns `x0..x1` (framed
    /// coordinates, never the frame) whose neighbour code hits `table`; whether any was removed.
    fn sweep(
        &mut self,
        (x0, x1): (usize, usize),
        (y0, y1): (usize, usize),
        table: &[bool; 256],
        marks: &mut Vec<usize>,
    ) -> bool {
        marks.clear();
        let pw = self.pw;
        let offsets = RING.map(|(dx, dy)| (dy * pw as isize + dx) as usize);
        for y in y0..y1 {
            for x in x0..x1 {
                let i = y * pw + x;
                if self.bits[i] == 0 {
                    continue;
                }
                let mut code = 0u8;
                for (bit, &o) in offsets.iter().enumerate() {
                    // i ± pw ± 1 stays inside: the frame surrounds every swept pixel.
                    let j = i.wrapping_add(o);
                    code |= self.bits[j] << bit;
                }
                if table[code as usize] {
                    marks.push(i);
                }
            }
        }
        for &i in marks.iter() {
            self.bits[i] = 0;
        }
        !marks.is_empty()
    }
}

/// Thinning of `a` by `method` until nothing changes or `max_rounds` rounds (one round = the
/// eight Golay passes, or the two Zhang–Suen sub-iterations) have run; `None` = no limit.
pub fn thinning(a: &Binary, method: ThinningMethod, max_rounds: Option<usize>) -> Binary {
    if a.width == 0 || a.height == 0 {
        return a.clone();
    }
    let mut framed = Framed::new(a);
    let (pw, ph) = (framed.pw, framed.ph);
    let mut marks = Vec::new();
    let mut rounds = 0;
    while max_rounds.is_none_or(|m| rounds < m) {
        rounds += 1;
        let mut changed = false;
        match method {
            ThinningMethod::Golay => {
                for table in &golay_tables() {
                    changed |= framed.sweep((1, pw - 1), (1, ph - 1), table, &mut marks);
                }
            }
            ThinningMethod::ZhangSuen => {
                // OpenCV leaves the image's outer pixels alone.
                let (xs, ys) = (
                    (2, pw.saturating_sub(2).max(2)),
                    (2, ph.saturating_sub(2).max(2)),
                );
                for table in &zhang_suen_tables() {
                    changed |= framed.sweep(xs, ys, table, &mut marks);
                }
            }
        }
        if !changed {
            break;
        }
    }
    framed.unframe(a.width, a.height)
}

/// Thickening: the complement of the thinning of the complement.
pub fn thickening(a: &Binary, method: ThinningMethod, max_rounds: Option<usize>) -> Binary {
    thinning(&a.complement(), method, max_rounds).complement()
}

// ---------------------------------------------------------------------------------------------
// Skeleton

/// Erosion with background outside the image: OpenCV's neutral-border erosion, cleared where
/// the element reaches past the image.
fn erode_inside(image: &Image, element: &StructuringElement) -> Binary {
    let mut out = Binary::from_mask_image(&erode(image, element, 1, MorphBorder::Neutral));
    let offsets = element.offsets();
    let (w, h) = (out.width as isize, out.height as isize);
    let min_dx = offsets.iter().map(|o| o.0).min().unwrap_or(0);
    let max_dx = offsets.iter().map(|o| o.0).max().unwrap_or(0);
    let min_dy = offsets.iter().map(|o| o.1).min().unwrap_or(0);
    let max_dy = offsets.iter().map(|o| o.1).max().unwrap_or(0);
    for y in 0..h {
        for x in 0..w {
            let inside = x + min_dx >= 0 && x + max_dx < w && y + min_dy >= 0 && y + max_dy < h;
            if !inside {
                out.bits[(y * w + x) as usize] = 0;
            }
        }
    }
    out
}

/// Lantuéjoul's skeleton of `a` by `element`: the skeleton and, per pixel, `k + 1` where it
/// belongs to the subset `Sₖ` (0 off the skeleton). The element must hold a cell other than
/// its anchor (else erosion never shrinks the set).
pub fn skeleton(a: &Binary, element: &StructuringElement) -> Result<(Binary, Vec<u16>), String> {
    if element.offsets().iter().all(|&o| o == (0, 0)) {
        return Err("the skeleton element needs a cell other than its anchor".into());
    }
    let reflected = element.reflected();
    let mut order = vec![0u16; a.bits.len()];
    let mut current = a.clone();
    // A ⊖ kB is inside the image shifted k times, so it is empty after max(w, h) + 1 steps.
    let limit = a.width.max(a.height) + 1;
    for k in 0..limit.min(u16::MAX as usize - 1) {
        if current.bits.iter().all(|&b| b == 0) {
            break;
        }
        let eroded = erode_inside(&current.to_image()?, element);
        let opened = Binary::from_mask_image(&dilate(
            &eroded.to_image()?,
            &reflected,
            1,
            MorphBorder::Neutral,
        ));
        for ((o, &c), &p) in order.iter_mut().zip(&current.bits).zip(&opened.bits) {
            if c == 1 && p == 0 {
                *o = k as u16 + 1;
            }
        }
        current = eroded;
    }
    let skeleton = Binary {
        bits: order.iter().map(|&o| u8::from(o > 0)).collect(),
        ..a.clone()
    };
    Ok((skeleton, order))
}

// ---------------------------------------------------------------------------------------------
// Operators

params! {
    /// Parameters of `filter.hit_or_miss`.
    pub struct HitOrMissParams {
        /// The element, rows of 1 (must be foreground), −1 (must be background) and 0
        /// (ignored), at most 255×255; shorter rows are padded with 0. Default: the 3×3
        /// `[[0, 1, 0], [1, −1, 1], [0, 1, 0]]` (a background pixel with four foreground
        /// neighbours).
        element: Vec<Vec<i32>> = vec![vec![0, 1, 0], vec![1, -1, 1], vec![0, 1, 0]],
        /// Anchor `[x, y]` inside the element, px; default none: the centre `(⌊w/2⌋, ⌊h/2⌋)`.
        anchor: Option<[u32; 2]> = None,
    }
}

/// Hit-or-miss transform (`filter.hit_or_miss`). See [`hit_or_miss`].
#[derive(Debug, Clone, PartialEq)]
pub struct HitOrMiss {
    element: HitMissElement,
}

fn anchor_of(anchor: Option<[u32; 2]>) -> Option<(usize, usize)> {
    anchor.map(|[x, y]| (x as usize, y as usize))
}

const INPUT_DOC: &str = "Binary image, gray u8 (nonzero = foreground).";

fn input_ports() -> Vec<PortSpec> {
    vec![PortSpec::new("image", PortType::Image, INPUT_DOC)]
}

fn binary_in(inputs: &Inputs<'_>) -> Result<Binary, OpError> {
    Binary::from_image(inputs.image("image")?).map_err(|e| OpError::input("image", e))
}

fn binary_out(b: &Binary) -> Result<Value, OpError> {
    b.to_image().map(Value::image).map_err(OpError::failed)
}

impl Op for HitOrMiss {
    type Params = HitOrMissParams;
    const ID: &'static str = "filter.hit_or_miss";
    const SUMMARY: &'static str =
        "Marks the pixels where a pattern of foreground and background cells fits a binary image.";
    const DOC: &'static str = r#"
Hit-or-miss transform of a binary image (gray u8, nonzero = foreground) by a three-valued
element: 1 = the cell must lie on foreground, −1 = on background, 0 = ignored. The output is 255
where the element, anchored on the pixel, fits, else 0.

Method: `erode(A, {cells = 1}) ∧ erode(¬A, {cells = −1})` with the van Herk / Gil-Werman erosion
of `filter.erode`, exactly OpenCV's `morphologyEx(MORPH_HITMISS)` (same element convention, same
anchor, cells off the image satisfy their condition as with OpenCV's default border). An element
without 1 (or without −1) cells leaves that condition true everywhere, as OpenCV. Unlike OpenCV,
the input is binarized first (OpenCV complements the raw bytes), so only 0/255 inputs agree
bit for bit.

Reference: J. Serra, Image Analysis and Mathematical Morphology, 1982; OpenCV `cv::morphologyEx`
with `MORPH_HITMISS`.

Example:
    "ends": (op: "filter.hit_or_miss", inputs: { "image": "mask.image" }, params: (element: [[-1, -1, -1], [-1, 1, -1], [0, 1, 0]])),
"#;

    fn inputs() -> Vec<PortSpec> {
        input_ports()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "255 where the element fits, else 0 (gray u8, input size).",
        )]
    }

    fn new(params: HitOrMissParams) -> Result<Self, String> {
        let element = HitMissElement::new(&params.element, anchor_of(params.anchor))
            .map_err(|e| format!("`element`: {e}"))?;
        Ok(HitOrMiss { element })
    }
}

impl Operator for HitOrMiss {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let a = binary_in(inputs)?;
        let out = hit_or_miss(&a, &self.element).map_err(OpError::failed)?;
        Ok(Outputs::new().with("image", binary_out(&out)?))
    }
}

params! {
    /// Parameters of `filter.thinning` and `filter.thickening`.
    pub struct ThinningParams {
        /// "golay" (eight rotated Golay L elements, Gonzalez & Woods) or "zhang_suen"
        /// (OpenCV `ximgproc::thinning`).
        method: ThinningMethod = ThinningMethod::Golay,
        /// Most rounds (eight Golay passes, or two Zhang–Suen sub-iterations, each), up to
        /// 1048576; default none: until nothing changes.
        max_iterations: Option<u32> = None,
    }
}

fn check_rounds(max_iterations: Option<u32>) -> Result<Option<usize>, String> {
    match max_iterations {
        Some(m) if m > MAX_ROUNDS => Err(format!(
            "`max_iterations` must be at most {MAX_ROUNDS}, got {m}"
        )),
        other => Ok(other.map(|m| m as usize)),
    }
}

/// Thinning (`filter.thinning`). See [`thinning`].
#[derive(Debug, Clone, PartialEq)]
pub struct Thinning {
    method: ThinningMethod,
    rounds: Option<usize>,
}

/// Thickening (`filter.thickening`). See [`thickening`].
#[derive(Debug, Clone, PartialEq)]
pub struct Thickening {
    method: ThinningMethod,
    rounds: Option<usize>,
}

impl Op for Thinning {
    type Params = ThinningParams;
    const ID: &'static str = "filter.thinning";
    const SUMMARY: &'static str =
        "Thins the foreground of a binary image to one-pixel-wide curves.";
    const DOC: &'static str = concat!(
        r#"
Iterative thinning of a binary image (gray u8, nonzero = foreground), output 0/255 gray u8.
"#,
        r#"
Methods:
- "golay" (default): sequential thinning `A ⊗ B = A − (A ⊛ B)` by the eight Golay L elements
  B¹…B⁸ in turn (B¹ has its top row background, its centre and bottom row foreground; each next
  is the previous turned 45° clockwise), a round being the eight passes, until a round removes
  nothing. Pixels outside the image are background (R. C. Gonzalez and R. E. Woods, Digital
  Image Processing, thinning by hit-or-miss).
- "zhang_suen": T. Y. Zhang and C. Y. Suen, "A fast parallel algorithm for thinning digital
  patterns", CACM 27(3), 1984, as OpenCV's `ximgproc::thinning(THINNING_ZHANGSUEN)`: two
  sub-iterations removing the contour pixels with 2..=6 foreground neighbours, one 0→1
  transition around them and each sub-iteration's direction condition; the outermost pixel
  frame of the image is never changed, as in OpenCV.
`max_iterations` stops after that many rounds. Each pass is a 256-entry table lookup of the
pixel's 8-neighbour code; deterministic.

Example:
    "lines": (op: "filter.thinning", inputs: { "image": "mask.image" }, params: (method: "zhang_suen")),
"#
    );

    fn inputs() -> Vec<PortSpec> {
        input_ports()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The thinned foreground, 0/255 gray u8.",
        )]
    }

    fn new(params: ThinningParams) -> Result<Self, String> {
        Ok(Thinning {
            method: params.method,
            rounds: check_rounds(params.max_iterations)?,
        })
    }
}

impl Operator for Thinning {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let a = binary_in(inputs)?;
        Ok(Outputs::new().with(
            "image",
            binary_out(&thinning(&a, self.method, self.rounds))?,
        ))
    }
}

impl Op for Thickening {
    type Params = ThinningParams;
    const ID: &'static str = "filter.thickening";
    const SUMMARY: &'static str =
        "Thickens the foreground of a binary image: the complement of thinning the background.";
    const DOC: &'static str = concat!(
        r#"
Thickening of a binary image (gray u8, nonzero = foreground), output 0/255 gray u8, defined as
the complement of the thinning of the complement (Gonzalez & Woods), with the same methods and
`max_iterations` as `filter.thinning`. With "golay" pixels outside the image count as
background of the complement, i.e. foreground of the input, so the background is thinned away
from the image border too.
"#,
        r#"
Example:
    "grow": (op: "filter.thickening", inputs: { "image": "mask.image" }, params: (max_iterations: 3)),
"#
    );

    fn inputs() -> Vec<PortSpec> {
        input_ports()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The thickened foreground, 0/255 gray u8.",
        )]
    }

    fn new(params: ThinningParams) -> Result<Self, String> {
        Ok(Thickening {
            method: params.method,
            rounds: check_rounds(params.max_iterations)?,
        })
    }
}

impl Operator for Thickening {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let a = binary_in(inputs)?;
        Ok(Outputs::new().with(
            "image",
            binary_out(&thickening(&a, self.method, self.rounds))?,
        ))
    }
}

params! {
    /// Parameters of `filter.skeleton`.
    pub struct SkeletonParams {
        /// Element shape B: "rect", "cross" or "ellipse".
        shape: Shape = Shape::Rect,
        /// Element size `[width, height]`, px, each 1..=255 (ignored when `element` is given).
        ksize: [u32; 2] = [3, 3] => [min = 1, max = 255, unit = "px"],
        /// Custom element B, rows of 0/1 (nonzero = part of B), at most 255×255; default `[]`:
        /// use `shape` and `ksize`.
        element: Vec<Vec<u8>> = Vec::new(),
        /// Anchor `[x, y]` inside the element box, px; default none: the centre.
        anchor: Option<[u32; 2]> = None,
    }
}

/// Morphological skeleton (`filter.skeleton`). See [`skeleton`].
#[derive(Debug, Clone, PartialEq)]
pub struct Skeleton {
    element: StructuringElement,
}

impl Op for Skeleton {
    type Params = SkeletonParams;
    const ID: &'static str = "filter.skeleton";
    const SUMMARY: &'static str =
        "Morphological skeleton of a binary image by Lantuéjoul's formula.";
    const DOC: &'static str = r#"
Skeleton of a binary image A (gray u8, nonzero = foreground) by a structuring element B:
`S = ∪ₖ Sₖ` with `Sₖ = (A ⊖ kB) − (A ⊖ kB) ∘ B`, `A ⊖ kB` being k successive erosions and `∘`
the opening, for k = 0, 1, … until `A ⊖ kB` is empty (Lantuéjoul; Serra, Image Analysis and
Mathematical Morphology, 1982; Gonzalez & Woods). Erosion is `{x : x + B ⊆ A}` with pixels
outside the image background; dilation (inside the opening) is `{a + b}`, i.e. OpenCV's
`dilate` with the reflected element, so asymmetric elements and anchors are true openings.
The subsets are disjoint and `A = ∪ₖ Sₖ ⊕ kB`: output `order` holds k + 1 on the pixels of
`Sₖ` (0 elsewhere), which with B reconstructs A. The element needs a cell other than its
anchor. Runs one erosion and one dilation (van Herk / direct, as `filter.erode`) per k.

Example:
    "bones": (op: "filter.skeleton", inputs: { "image": "mask.image" }, params: (shape: "cross")),
"#;

    fn inputs() -> Vec<PortSpec> {
        input_ports()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("image", PortType::Image, "The skeleton S, 0/255 gray u8."),
            PortSpec::new(
                "order",
                PortType::Image,
                "k + 1 on the pixels of the subset Sₖ, 0 off the skeleton (gray u16).",
            ),
        ]
    }

    fn new(params: SkeletonParams) -> Result<Self, String> {
        let anchor = anchor_of(params.anchor);
        let element = if params.element.is_empty() {
            let [w, h] = params.ksize;
            if !(1..=MAX_ELEMENT as u32).contains(&w) || !(1..=MAX_ELEMENT as u32).contains(&h) {
                return Err(format!(
                    "`ksize` sides must be between 1 and {MAX_ELEMENT}, got [{w}, {h}]"
                ));
            }
            let e = StructuringElement::new(params.shape, w as usize, h as usize)
                .ok_or_else(|| "`ksize` must be at least 1".to_string())?;
            match anchor {
                Some((x, y)) => e.with_anchor(x, y).map_err(|e| format!("`anchor`: {e}"))?,
                None => e,
            }
        } else {
            if params.element.len() > MAX_ELEMENT
                || params.element.iter().any(|r| r.len() > MAX_ELEMENT)
            {
                return Err(format!("`element` sides must be at most {MAX_ELEMENT}"));
            }
            StructuringElement::from_mask(&params.element, anchor)
                .map_err(|e| format!("`element`: {e}"))?
        };
        if element.offsets().iter().all(|&o| o == (0, 0)) {
            return Err("the element needs a cell other than its anchor".into());
        }
        Ok(Skeleton { element })
    }
}

impl Operator for Skeleton {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let a = binary_in(inputs)?;
        let (s, order) = skeleton(&a, &self.element).map_err(OpError::failed)?;
        let order = Image::from_u16(a.width, a.height, Channels::Gray, order)
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("image", binary_out(&s)?)
            .with("order", Value::image(order)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::randoms;
    use proptest::prelude::*;

    fn binary(rows: &[&str]) -> Binary {
        let width = rows.first().map_or(0, |r| r.len());
        Binary {
            width,
            height: rows.len(),
            bits: rows
                .iter()
                .flat_map(|r| r.bytes().map(|b| u8::from(b == b'1')))
                .collect(),
        }
    }

    fn rows(b: &Binary) -> Vec<String> {
        b.bits
            .chunks(b.width.max(1))
            .map(|r| r.iter().map(|&v| if v == 1 { '1' } else { '0' }).collect())
            .collect()
    }

    fn random_binary(w: usize, h: usize, density: f64, seed: u64) -> Binary {
        Binary {
            width: w,
            height: h,
            bits: randoms(seed, w * h)
                .iter()
                .map(|&r| u8::from(r < density))
                .collect(),
        }
    }

    fn subset(a: &Binary, b: &Binary) -> bool {
        a.bits.iter().zip(&b.bits).all(|(&x, &y)| x <= y)
    }

    /// The 10×8 input `(7x + 13y + xy) mod 5 < 2` of the OpenCV comparison.
    fn opencv_input() -> Binary {
        binary(&[
            "1001010010",
            "0100101001",
            "1100011000",
            "0000000000",
            "0001100011",
            "1001010010",
            "0100101001",
            "1100011000",
        ])
    }

    #[test]
    fn hit_or_miss_matches_opencv() {
        // cv2.morphologyEx(img, cv2.MORPH_HITMISS, kernel), OpenCV 5.0.
        let cases: [(Vec<Vec<i32>>, [&str; 8]); 4] = [
            (
                vec![vec![0, 1, 0], vec![1, -1, 1], vec![0, 1, 0]],
                [
                    "0000100001",
                    "1000010000",
                    "0000000000",
                    "0000000000",
                    "0000000000",
                    "0000100001",
                    "1000010000",
                    "0000000000",
                ],
            ),
            (
                vec![vec![1, 1, 0], vec![-1, 1, -1]],
                [
                    "1001010010",
                    "0000000000",
                    "0000000000",
                    "0000000000",
                    "0000000000",
                    "0000000000",
                    "0000000000",
                    "0000000000",
                ],
            ),
            (
                vec![vec![-1, -1, -1], vec![0, 1, 0], vec![1, 1, 1]],
                [
                    "0000000000",
                    "0000000000",
                    "0000000000",
                    "0000000000",
                    "0000000000",
                    "0000000000",
                    "0000000000",
                    "0000000000",
                ],
            ),
            (
                vec![vec![1, 0, 0, -1]],
                [
                    "1100010000",
                    "0100001000",
                    "0111000110",
                    "1100000000",
                    "1100011000",
                    "1100010000",
                    "0100001000",
                    "0111000110",
                ],
            ),
        ];
        let a = opencv_input();
        for (kernel, expected) in cases {
            let e = HitMissElement::new(&kernel, None).unwrap();
            assert_eq!(rows(&hit_or_miss(&a, &e).unwrap()), expected, "{kernel:?}");
        }
    }

    #[test]
    fn hit_or_miss_hand_cases() {
        // An isolated point detector finds exactly the isolated points.
        let a = binary(&["10000", "00010", "00011", "00000"]);
        let e = HitMissElement::new(&[vec![-1, -1, -1], vec![-1, 1, -1], vec![-1, -1, -1]], None)
            .unwrap();
        assert_eq!(
            rows(&hit_or_miss(&a, &e).unwrap()),
            ["10000", "00000", "00000", "00000"]
        );
        // All-ignore element: everything hits.
        let e = HitMissElement::new(&[vec![0]], None).unwrap();
        assert!(hit_or_miss(&a, &e).unwrap().bits.iter().all(|&b| b == 1));
        assert!(HitMissElement::new(&[vec![2]], None).is_err());
        assert!(HitMissElement::new(&[], None).is_err());
        assert!(HitMissElement::new(&[vec![1, 0]], Some((2, 0))).is_err());
        let empty = binary(&[]);
        let e = HitMissElement::new(&[vec![1, -1]], None).unwrap();
        assert_eq!(hit_or_miss(&empty, &e).unwrap().bits.len(), 0);
    }

    #[test]
    fn golay_elements_are_gonzalez_woods() {
        let cells = |(fg, bg): (u8, u8)| -> [i32; 9] {
            let mut m = [0; 9];
            m[4] = 1;
            for (bit, (dx, dy)) in RING.iter().enumerate() {
                let i = ((dy + 1) * 3 + dx + 1) as usize;
                m[i] = if fg >> bit & 1 == 1 {
                    1
                } else if bg >> bit & 1 == 1 {
                    -1
                } else {
                    0
                };
            }
            m
        };
        let l = golay_elements();
        assert_eq!(cells(l[0]), [-1, -1, -1, 0, 1, 0, 1, 1, 1]);
        assert_eq!(cells(l[1]), [0, -1, -1, 1, 1, -1, 1, 1, 0]);
        assert_eq!(cells(l[2]), [1, 0, -1, 1, 1, -1, 1, 0, -1]);
        assert_eq!(cells(l[4]), [1, 1, 1, 0, 1, 0, -1, -1, -1]);
    }

    #[test]
    fn thinning_a_bar_leaves_a_line() {
        let a = binary(&[
            "000000000000",
            "011111111110",
            "011111111110",
            "011111111110",
            "000000000000",
        ]);
        for method in [ThinningMethod::Golay, ThinningMethod::ZhangSuen] {
            let t = thinning(&a, method, None);
            assert!(subset(&t, &a));
            // The middle row survives; one pixel thick away from the ends (Golay leaves short
            // spurs at the corners).
            assert_eq!(
                &t.bits[2 * 12 + 3..2 * 12 + 9],
                &[1; 6],
                "{method:?} {:?}",
                rows(&t)
            );
            for x in 2..10 {
                let column: u8 = (0..5).map(|y| t.bits[y * 12 + x]).sum();
                assert!(column <= 1, "{method:?} {:?}", rows(&t));
            }
            assert_eq!(thinning(&t, method, None), t, "idempotent");
        }
        assert_eq!(thinning(&a, ThinningMethod::Golay, Some(0)), a);
        // One round of eight passes strips the bar's top and bottom rows.
        let once = thinning(&a, ThinningMethod::Golay, Some(1));
        assert!(once.bits.iter().map(|&b| b as usize).sum::<usize>() < 30);
    }

    #[test]
    fn zhang_suen_keeps_the_frame() {
        let a = Binary {
            width: 6,
            height: 5,
            bits: vec![1; 30],
        };
        let t = thinning(&a, ThinningMethod::ZhangSuen, None);
        for y in 0..5 {
            for x in 0..6 {
                if x == 0 || y == 0 || x == 5 || y == 4 {
                    assert_eq!(t.bits[y * 6 + x], 1);
                }
            }
        }
        // Golay thinning of a full image shrinks it (outside is background).
        let g = thinning(&a, ThinningMethod::Golay, None);
        assert!(g.bits.iter().filter(|&&b| b == 1).count() < 30);
        for tiny in [binary(&[]), binary(&["1"]), binary(&["11"])] {
            assert_eq!(thinning(&tiny, ThinningMethod::ZhangSuen, None), tiny);
            assert!(subset(&thinning(&tiny, ThinningMethod::Golay, None), &tiny));
        }
    }

    #[test]
    fn thickening_is_dual_thinning() {
        let a = random_binary(17, 13, 0.4, 3);
        for method in [ThinningMethod::Golay, ThinningMethod::ZhangSuen] {
            let t = thickening(&a, method, Some(2));
            assert!(subset(&a, &t));
            assert_eq!(t.complement(), thinning(&a.complement(), method, Some(2)));
        }
    }

    fn reconstruct(order: &[u16], width: usize, height: usize, e: &StructuringElement) -> Binary {
        let reflected = e.reflected();
        let top = order.iter().copied().max().unwrap_or(0);
        let mut union = vec![0u8; order.len()];
        for k in 1..=top {
            let mut s = Binary {
                width,
                height,
                bits: order.iter().map(|&o| u8::from(o == k)).collect(),
            };
            for _ in 1..k {
                let img = s.to_image().unwrap();
                s = Binary::from_mask_image(&dilate(&img, &reflected, 1, MorphBorder::Neutral));
            }
            for (u, &b) in union.iter_mut().zip(&s.bits) {
                *u |= b;
            }
        }
        Binary {
            width,
            height,
            bits: union,
        }
    }

    #[test]
    fn skeleton_hand_cases() {
        let rect = StructuringElement::new(Shape::Rect, 3, 3).unwrap();
        let a = binary(&["00000", "01110", "01110", "01110", "00000"]);
        let (s, order) = skeleton(&a, &rect).unwrap();
        assert_eq!(rows(&s), ["00000", "00000", "00100", "00000", "00000"]);
        assert_eq!(order[12], 2);
        // A single pixel is its own skeleton (S₀); a line too.
        let line = binary(&["0000", "0110", "0000"]);
        assert_eq!(skeleton(&line, &rect).unwrap().0, line);
        let only = StructuringElement::from_mask(&[vec![1]], None).unwrap();
        assert!(skeleton(&a, &only).is_err());
        let empty = binary(&[]);
        assert_eq!(skeleton(&empty, &rect).unwrap().0, empty);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        #[test]
        fn skeleton_reconstructs(
            w in 1usize..20,
            h in 1usize..20,
            density in 0.3f64..0.9,
            shape in prop::sample::select(vec![Shape::Rect, Shape::Cross, Shape::Ellipse]),
            (kw, kh) in (1usize..3, 1usize..3),
            seed in any::<u64>(),
        ) {
            let a = random_binary(w, h, density, seed);
            let e = StructuringElement::new(shape, 2 * kw + 1, 2 * kh + 1)
                .unwrap();
            let (s, order) = skeleton(&a, &e).unwrap();
            prop_assert!(subset(&s, &a));
            prop_assert_eq!(reconstruct(&order, w, h, &e), a);
        }

        #[test]
        fn thinning_converges_inside(
            w in 1usize..24,
            h in 1usize..24,
            density in 0.2f64..0.9,
            zhang in any::<bool>(),
            seed in any::<u64>(),
        ) {
            let method = if zhang { ThinningMethod::ZhangSuen } else { ThinningMethod::Golay };
            let a = random_binary(w, h, density, seed);
            let t = thinning(&a, method, None);
            prop_assert!(subset(&t, &a));
            prop_assert_eq!(thinning(&t, method, None), t.clone());
            // The hit-or-miss of every Golay element finds nothing left to remove.
            if !zhang {
                for (fg, bg) in golay_elements() {
                    let mut cells = vec![vec![0i32; 3]; 3];
                    cells[1][1] = 1;
                    for (bit, (dx, dy)) in RING.iter().enumerate() {
                        let v = if fg >> bit & 1 == 1 { 1 } else if bg >> bit & 1 == 1 { -1 } else { 0 };
                        cells[(dy + 1) as usize][(dx + 1) as usize] = v;
                    }
                    // Hit-or-miss with OpenCV's border differs at the image edge; check inside.
                    let e = HitMissElement::new(&cells, None).unwrap();
                    let hits = hit_or_miss(&t, &e).unwrap();
                    for y in 1..h.saturating_sub(1) {
                        for x in 1..w.saturating_sub(1) {
                            prop_assert_eq!(hits.bits[y * w + x], 0);
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn operators_run_and_check_inputs() {
        let img = opencv_input().to_image().unwrap();
        let specs = Thinning::inputs();
        let ctx = RunContext {
            node: "t".into(),
            threads: 1,
            element: None,
        };
        let run = |op: &dyn Operator, image: Image, port: &str| {
            let values = [Some(Value::image(image))];
            op.run(&ctx, &Inputs::new(&specs, &values))
                .map(|mut out| match out.take(port) {
                    Some(Value::Image(got)) => (*got).clone(),
                    _ => panic!("expected an image"),
                })
        };
        let a = opencv_input();
        let t = run(
            &Thinning::new(ThinningParams::default()).unwrap(),
            img.clone(),
            "image",
        );
        assert_eq!(
            t.unwrap(),
            thinning(&a, ThinningMethod::Golay, None)
                .to_image()
                .unwrap()
        );
        let t = run(
            &Thickening::new(ThinningParams::default()).unwrap(),
            img.clone(),
            "image",
        );
        assert_eq!(
            t.unwrap(),
            thickening(&a, ThinningMethod::Golay, None)
                .to_image()
                .unwrap()
        );
        let h = run(
            &HitOrMiss::new(HitOrMissParams::default()).unwrap(),
            img.clone(),
            "image",
        );
        assert_eq!(h.unwrap().as_u8().unwrap()[4], 255);
        let sk = Skeleton::new(SkeletonParams::default()).unwrap();
        let order = run(&sk, img.clone(), "order").unwrap();
        assert_eq!(order.depth(), ocellus_engine::value::Depth::U16);
        let rgb = Image::from_u8(2, 2, Channels::Rgb, vec![0; 12]).unwrap();
        let err = run(&sk, rgb, "image").unwrap_err();
        assert!(err.to_string().contains("gray u8"), "{err}");
        // Parameter checks.
        assert!(
            HitOrMiss::new(HitOrMissParams {
                element: vec![vec![3]],
                anchor: None
            })
            .is_err()
        );
        assert!(
            Skeleton::new(SkeletonParams {
                ksize: [1, 1],
                ..SkeletonParams::default()
            })
            .is_err()
        );
        assert!(
            Skeleton::new(SkeletonParams {
                ksize: [256, 3],
                ..SkeletonParams::default()
            })
            .is_err()
        );
        assert!(
            Thinning::new(ThinningParams {
                max_iterations: Some(u32::MAX),
                ..ThinningParams::default()
            })
            .is_err()
        );
    }
}
