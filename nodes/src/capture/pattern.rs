//! `capture.pattern`: synthetic images — a test card, a checkerboard, seeded noise, ramps and a
//! Siemens star — for trying graphs without data and for testing filters.
//!
//! Every pixel is a pure function of its coordinates (and the seed), computed independently, so
//! rows are rendered in parallel and the output is bit-identical for any thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Depth, Image, PixelData, PixelFormat, Value, ValueError};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

/// Largest width or height.
pub const MAX_SIDE: u32 = 32768;

/// Largest pixel count (2²⁸).
pub const MAX_PIXELS: u64 = 1 << 28;

/// Rows per parallel task.
const ROWS_PER_TASK: usize = 16;

/// Mid gray: the test card's background and the Siemens star's surround.
const MID_GRAY: f32 = 0.5;

param_enum! {
    /// What to draw.
    pub enum PatternKind {
        /// A broadcast-style test card (see [`Drawing::TestCard`]).
        TestCard = "test_card",
        /// Black and white squares, black at the top left.
        Checkerboard = "checkerboard",
        /// Uniform white noise from a seed.
        Noise = "noise",
        /// Ramps: luminance left to right, blue top to bottom.
        Gradient = "gradient",
        /// Black and white sectors around the centre.
        SiemensStar = "siemens_star",
    }
}

param_enum! {
    /// Channel layout of the output.
    pub enum PatternChannels {
        /// One luma channel (BT.601 luma of the colour pattern).
        Gray = "gray",
        /// Red, green, blue.
        Rgb = "rgb",
        /// Red, green, blue and an opaque alpha.
        Rgba = "rgba",
    }
}

param_enum! {
    /// Sample type of the output.
    pub enum PatternDepth {
        /// 0–255.
        U8 = "u8",
        /// 0–65535.
        U16 = "u16",
        /// 0.0–1.0.
        F32 = "f32",
    }
}

params! {
    /// Parameters of `capture.pattern`.
    pub struct PatternParams {
        /// What to draw: "test_card", "checkerboard", "noise", "gradient" or "siemens_star".
        kind: PatternKind = PatternKind::TestCard,
        /// Image width (0 gives an empty image).
        width: u32 = 640 => [min = 0, max = 32768, unit = "px"],
        /// Image height (0 gives an empty image).
        height: u32 = 480 => [min = 0, max = 32768, unit = "px"],
        /// Channel layout: "gray", "rgb" or "rgba" (alpha opaque).
        channels: PatternChannels = PatternChannels::Rgb,
        /// Sample type: "u8", "u16" (full range) or "f32" (0 to 1).
        depth: PatternDepth = PatternDepth::U8,
        /// Checkerboard square side, and test-card grid spacing.
        square: u32 = 32 => [min = 1, unit = "px"],
        /// Siemens star: number of black spokes (as many white ones alternate with them).
        spokes: u32 = 36 => [min = 2, max = 720],
        /// Noise: the seed; the same seed always gives the same image.
        seed: u64 = 0,
    }
}

/// What to draw, with only the settings that kind uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Drawing {
    /// A test card in the manner of broadcast cards and camera charts, laid out in coordinates
    /// relative to the shorter side (so it looks the same at every resolution), centred:
    /// - mid-gray background with white grid lines every `square` px (one line through the
    ///   centre) and a castellated black/white frame along the image border;
    /// - four registration marks near the corners: discs split into black and white quadrants;
    /// - a central circle (radius 0.4 of the shorter side, white rim) holding, top to bottom:
    ///   bars slanted 5° from vertical (slanted-edge sharpness), 100 % colour bars (white,
    ///   yellow, cyan, green, magenta, red, blue, black), six gray steps (0, 0.2, …, 1),
    ///   vertical line gratings of periods 8, 6, 4, 3 and 2 px, a black|white split with a
    ///   mid-gray centre cross, horizontal gratings of the same periods, a continuous gray ramp,
    ///   a hue sweep, and bars at 45° (diagonal edges).
    ///
    /// Slanted and curved edges are antialiased (box-filtered distance to the edge); gratings,
    /// bars and steps are pixel-aligned and crisp.
    TestCard {
        /// Grid spacing and frame block length, px (≥ 1).
        square: u32,
    },
    /// Squares of side `square` px, black at the top left.
    Checkerboard {
        /// Square side, px (≥ 1).
        square: u32,
    },
    /// Independent uniform samples: sample `c` of pixel `i = y·width + x` is drawn from
    /// `splitmix64(splitmix64(seed) ^ (4i + c))` (the top 8, 16 or 24 bits), so the noise is
    /// the same at any thread count, and the gray image equals the red channel. Alpha is opaque.
    Noise {
        /// Seed.
        seed: u64,
    },
    /// Ramps from 0 at the first column (row) to 1 at the last: red and green (the luminance)
    /// left to right, blue top to bottom. The gray image is the horizontal ramp.
    Gradient,
    /// A Siemens star: `spokes` black and `spokes` white sectors of equal angle around the image
    /// centre, the first white one starting at angle 0 (pointing right, clockwise on screen),
    /// inside a disc of radius 0.45 of the shorter side on a mid-gray background. Pixels
    /// crossed by an edge are the average of 4×4 samples.
    SiemensStar {
        /// Black spokes, 2..=720.
        spokes: u32,
    },
}

/// Synthetic test images (`capture.pattern`). See [`Drawing`].
#[derive(Debug, Clone, PartialEq)]
pub struct Pattern {
    drawing: Drawing,
    width: usize,
    height: usize,
    format: PixelFormat,
}

impl Op for Pattern {
    type Params = PatternParams;
    const ID: &'static str = "capture.pattern";
    const SUMMARY: &'static str =
        "Generates a synthetic image: test card, checkerboard, noise, gradient or Siemens star.";
    const DOC: &'static str = r#"
Generates a synthetic image of the requested size and pixel format.

Kinds:
- "test_card": grid, castellated frame, corner registration marks and a central circle with
  slanted bars, colour bars, gray steps, line gratings of periods 8 to 2 px, a centre cross, a
  gray ramp, a hue sweep and 45° bars. Layout relative to the shorter side, so it is the same
  picture at any resolution; grid spacing `square` px.
- "checkerboard": squares of `square` px, black at the top left.
- "noise": uniform white noise, each sample from a counter-based hash (SplitMix64) of `seed`
  and the sample index: reproducible, and the same at any thread count.
- "gradient": red and green ramp 0 → 1 left to right, blue 0 → 1 top to bottom; gray is the
  horizontal ramp.
- "siemens_star": `spokes` black and white sector pairs in a disc on mid gray, antialiased by
  4×4 supersampling.

Values: u8 0–255, u16 0–65535, f32 0–1; gray output is the BT.601 luma of the colour pattern;
alpha is opaque. Parameters that the chosen kind does not use must keep their defaults.

References: Philips PM5544 and EBU test cards; ISO 12233 (slanted edges, Siemens star);
SplitMix64 (Steele, Lea, Flood: "Fast splittable pseudorandom number generators", OOPSLA 2014).

Example:
    "card": (op: "capture.pattern", params: (kind: "test_card", width: 1920, height: 1080)),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The generated image, `width` × `height` in the requested format.",
        )]
    }

    fn new(params: PatternParams) -> Result<Self, String> {
        let defaults = PatternParams::default();
        let only_for = |name: &str, kinds: &str| {
            Err(format!(
                "`{name}` applies only to {kinds} (kind is \"{}\")",
                params.kind.name()
            ))
        };
        let drawing = match params.kind {
            PatternKind::TestCard => Drawing::TestCard {
                square: params.square,
            },
            PatternKind::Checkerboard => Drawing::Checkerboard {
                square: params.square,
            },
            PatternKind::Noise => Drawing::Noise { seed: params.seed },
            PatternKind::Gradient => Drawing::Gradient,
            PatternKind::SiemensStar => Drawing::SiemensStar {
                spokes: params.spokes,
            },
        };
        let uses_square = matches!(
            drawing,
            Drawing::TestCard { .. } | Drawing::Checkerboard { .. }
        );
        if !uses_square && params.square != defaults.square {
            return only_for("square", "kinds \"checkerboard\" and \"test_card\"");
        }
        if !matches!(drawing, Drawing::SiemensStar { .. }) && params.spokes != defaults.spokes {
            return only_for("spokes", "kind \"siemens_star\"");
        }
        if !matches!(drawing, Drawing::Noise { .. }) && params.seed != defaults.seed {
            return only_for("seed", "kind \"noise\"");
        }
        if params.square == 0 {
            return Err("`square` must be ≥ 1 px".into());
        }
        if !(2..=720).contains(&params.spokes) {
            return Err(format!(
                "`spokes` must be between 2 and 720, got {}",
                params.spokes
            ));
        }
        for (name, side) in [("width", params.width), ("height", params.height)] {
            if side > MAX_SIDE {
                return Err(format!("`{name}` must be ≤ {MAX_SIDE} px, got {side}"));
            }
        }
        let pixels = u64::from(params.width) * u64::from(params.height);
        if pixels > MAX_PIXELS {
            return Err(format!(
                "{}×{} is {pixels} pixels, more than the limit of 2^28 ({MAX_PIXELS})",
                params.width, params.height
            ));
        }
        let channels = match params.channels {
            PatternChannels::Gray => Channels::Gray,
            PatternChannels::Rgb => Channels::Rgb,
            PatternChannels::Rgba => Channels::Rgba,
        };
        let depth = match params.depth {
            PatternDepth::U8 => Depth::U8,
            PatternDepth::U16 => Depth::U16,
            PatternDepth::F32 => Depth::F32,
        };
        Ok(Pattern {
            drawing,
            width: params.width as usize,
            height: params.height as usize,
            format: PixelFormat { channels, depth },
        })
    }
}

impl Operator for Pattern {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = render(self.drawing, self.width, self.height, self.format)
            .map_err(|e| OpError::failed(format!("building the pattern image: {e}")))?;
        Ok(Outputs::new().with("image", Value::image(image)))
    }
}

/// Renders `drawing` as a `width` × `height` image of `format` (zero sizes give an empty image).
pub fn render(
    drawing: Drawing,
    width: usize,
    height: usize,
    format: PixelFormat,
) -> Result<Image, ValueError> {
    let samples = Image::sample_count(width, height, format.channels)?;
    let painter = Painter::new(drawing, width, height);
    let channels = format.channels;
    let data = match format.depth {
        Depth::U8 => PixelData::U8(paint::<u8>(&painter, samples, channels)),
        Depth::U16 => PixelData::U16(paint::<u16>(&painter, samples, channels)),
        Depth::F32 => PixelData::F32(paint::<f32>(&painter, samples, channels)),
    };
    Image::new(width, height, channels, data)
}

/// Output sample types.
trait Level: Copy + Default + Send + Sync {
    /// Full intensity (opaque alpha).
    const FULL: Self;
    /// An intensity in 0..=1 (clamped), rounded to nearest.
    fn from_unit(v: f32) -> Self;
    /// A uniform sample from 64 random bits (the top ones).
    fn from_bits(bits: u64) -> Self;
}

impl Level for u8 {
    const FULL: Self = u8::MAX;
    fn from_unit(v: f32) -> Self {
        (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
    }
    fn from_bits(bits: u64) -> Self {
        (bits >> 56) as u8
    }
}

impl Level for u16 {
    const FULL: Self = u16::MAX;
    fn from_unit(v: f32) -> Self {
        (v.clamp(0.0, 1.0) * 65535.0 + 0.5) as u16
    }
    fn from_bits(bits: u64) -> Self {
        (bits >> 48) as u16
    }
}

impl Level for f32 {
    const FULL: Self = 1.0;
    fn from_unit(v: f32) -> Self {
        v.clamp(0.0, 1.0)
    }
    fn from_bits(bits: u64) -> Self {
        // 24 bits: every value k / 2²⁴ is exact in f32.
        (bits >> 40) as f32 / 16_777_216.0
    }
}

/// Renders every sample, rows in parallel.
fn paint<T: Level>(painter: &Painter, samples: usize, channels: Channels) -> Vec<T> {
    let mut data = vec![T::default(); samples];
    let row_len = painter.width * channels.count();
    if row_len == 0 {
        return data;
    }
    data.par_chunks_mut(ROWS_PER_TASK * row_len)
        .enumerate()
        .for_each(|(task, rows)| {
            for (r, row) in rows.chunks_exact_mut(row_len).enumerate() {
                painter.paint_row(task * ROWS_PER_TASK + r, channels, row);
            }
        });
    data
}

/// SplitMix64's output function: a bijective 64-bit mix (also the counter-based hash of
/// `capture.moving_shapes`).
pub(crate) fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// BT.601 luma, exact for grays.
fn luma([r, g, b]: [f32; 3]) -> f32 {
    if r == g && g == b {
        r
    } else {
        0.299 * r + 0.587 * g + 0.114 * b
    }
}

/// Per-drawing precomputed state.
struct Painter {
    drawing: Drawing,
    width: usize,
    height: usize,
    card: Card,
    /// `splitmix64(seed)` for noise.
    seed_key: u64,
}

impl Painter {
    fn new(drawing: Drawing, width: usize, height: usize) -> Painter {
        let seed_key = match drawing {
            Drawing::Noise { seed } => splitmix64(seed),
            _ => 0,
        };
        let square = match drawing {
            Drawing::TestCard { square } => square.max(1) as usize,
            _ => 1,
        };
        Painter {
            drawing,
            width,
            height,
            card: Card::new(width, height, square),
            seed_key,
        }
    }

    fn paint_row<T: Level>(&self, y: usize, channels: Channels, row: &mut [T]) {
        let stride = channels.count();
        for (x, pixel) in row.chunks_exact_mut(stride).enumerate() {
            if let Drawing::Noise { .. } = self.drawing {
                let index = (y as u64 * self.width as u64 + x as u64) * 4;
                for (c, sample) in pixel.iter_mut().enumerate().take(3) {
                    *sample = T::from_bits(splitmix64(self.seed_key ^ (index + c as u64)));
                }
            } else if channels == Channels::Gray {
                pixel[0] = T::from_unit(self.gray(x, y));
            } else {
                let rgb = self.rgb(x, y);
                for (sample, v) in pixel.iter_mut().zip(rgb) {
                    *sample = T::from_unit(v);
                }
            }
            if channels == Channels::Rgba {
                pixel[3] = T::FULL;
            }
        }
    }

    fn gray(&self, x: usize, y: usize) -> f32 {
        match self.drawing {
            Drawing::Gradient => ramp(x, self.width),
            _ => luma(self.rgb(x, y)),
        }
    }

    fn rgb(&self, x: usize, y: usize) -> [f32; 3] {
        match self.drawing {
            Drawing::TestCard { .. } => self.card.rgb(x, y),
            Drawing::Checkerboard { square } => {
                let square = square.max(1) as usize;
                let white = (x / square + y / square) % 2 == 1;
                [if white { 1.0 } else { 0.0 }; 3]
            }
            Drawing::Gradient => {
                let u = ramp(x, self.width);
                [u, u, ramp(y, self.height)]
            }
            Drawing::SiemensStar { spokes } => [star(x, y, self.width, self.height, spokes); 3],
            // Noise is drawn from bits in `paint_row`; this is its mean.
            Drawing::Noise { .. } => [MID_GRAY; 3],
        }
    }
}

/// `i / (n − 1)`: 0 at the first position, 1 at the last (0 when there is one position).
fn ramp(i: usize, n: usize) -> f32 {
    if n > 1 {
        i as f32 / (n - 1) as f32
    } else {
        0.0
    }
}

/// The Siemens star's value at pixel (x, y).
fn star(x: usize, y: usize, width: usize, height: usize, spokes: u32) -> f32 {
    const SUBSAMPLES: usize = 4;
    let spokes = spokes.max(1);
    let whole_spokes = u64::from(spokes);
    let spokes = f64::from(spokes);
    let cx = width as f64 / 2.0;
    let cy = height as f64 / 2.0;
    let radius = 0.45 * width.min(height) as f64;
    // Sector k covers angles [k, k + 1)·π/spokes; odd sectors are black.
    let sector = |dx: f64, dy: f64| {
        dy.atan2(dx).rem_euclid(std::f64::consts::TAU) * spokes / std::f64::consts::PI
    };
    let value = |dx: f64, dy: f64| {
        if dx * dx + dy * dy > radius * radius {
            f64::from(MID_GRAY)
        } else if on_sector_boundary(dx, dy, whole_spokes) {
            // Subsample coordinates are exact dyadic fractions, so a sample can fall exactly
            // on a boundary along an axis or a diagonal; it counts half, which keeps the star's
            // symmetries exact.
            0.5
        } else if (sector(dx, dy).floor() as u64).is_multiple_of(2) {
            1.0
        } else {
            0.0
        }
    };
    let dx = x as f64 + 0.5 - cx;
    let dy = y as f64 + 0.5 - cy;
    let r = (dx * dx + dy * dy).sqrt();
    // A pixel lies within √½ px of its centre: if no edge (the rim, or a sector boundary, whose
    // distance is at least r·sin Δθ ≥ r·Δθ·2/π) comes that close, all subsamples agree.
    const CLEAR: f64 = 0.75;
    let t = sector(dx, dy);
    let to_boundary = t.fract().min(1.0 - t.fract()) * std::f64::consts::PI / spokes;
    let clear_of_rim = (r - radius).abs() > CLEAR;
    let clear_of_sectors = r * to_boundary * 2.0 / std::f64::consts::PI > CLEAR;
    if r > radius + CLEAR || (clear_of_rim && clear_of_sectors) {
        return value(dx, dy) as f32;
    }
    let step = 1.0 / SUBSAMPLES as f64;
    let mut sum = 0.0;
    for j in 0..SUBSAMPLES {
        for i in 0..SUBSAMPLES {
            let sx = x as f64 + (i as f64 + 0.5) * step - cx;
            let sy = y as f64 + (j as f64 + 0.5) * step - cy;
            sum += value(sx, sy);
        }
    }
    (sum / (SUBSAMPLES * SUBSAMPLES) as f64) as f32
}

/// Whether direction (dx, dy) from the star's centre is exactly a sector boundary (angle
/// kπ/spokes). With rational coordinates that can only happen at multiples of 45° (Niven's
/// theorem: the only rational tangents of rational multiples of π are 0 and ±1), which are
/// tested exactly; the centre itself counts as a boundary.
fn on_sector_boundary(dx: f64, dy: f64, spokes: u64) -> bool {
    if dx == 0.0 && dy == 0.0 {
        return true;
    }
    // Angle mπ/4 is a boundary when m·spokes/4 is an integer.
    if dy == 0.0 {
        true
    } else if dx == 0.0 {
        spokes.is_multiple_of(2)
    } else if dx.abs() == dy.abs() {
        spokes.is_multiple_of(4)
    } else {
        false
    }
}

/// The test card's layout for one image size.
struct Card {
    width: usize,
    height: usize,
    /// Pixels per card unit (the shorter side).
    unit: f32,
    /// Grid spacing, px.
    square: usize,
    /// Grid line width, px.
    line: usize,
    /// Frame width, px.
    frame: usize,
    /// Half extents in card units.
    half_w: f32,
    half_h: f32,
    /// Chord half-width of each band inside the central circle (the narrower end).
    band_half_widths: [f32; BAND_EDGES.len() - 1],
}

/// Radius of the central circle, card units.
const CIRCLE: f32 = 0.4;
/// Band edges inside the central circle, top to bottom, card units.
const BAND_EDGES: [f32; 10] = [
    -0.40, -0.31, -0.22, -0.13, -0.05, 0.05, 0.13, 0.22, 0.31, 0.40,
];
/// Grating periods, px, coarse to fine.
const GRATINGS: [usize; 5] = [8, 6, 4, 3, 2];
/// tan 5° and cos 5°: the slanted-edge angle.
const TAN_5_DEG: f32 = 0.087_488_66;
const COS_5_DEG: f32 = 0.996_194_7;
/// Corner registration marks: radius, and inset of their centres from the image edges.
const MARK_RADIUS: f32 = 0.08;
const MARK_INSET: f32 = 0.13;

const BLACK: [f32; 3] = [0.0; 3];
const WHITE: [f32; 3] = [1.0; 3];
const GRAY: [f32; 3] = [MID_GRAY; 3];
const COLOUR_BARS: [[f32; 3]; 8] = [
    WHITE,
    [1.0, 1.0, 0.0],
    [0.0, 1.0, 1.0],
    [0.0, 1.0, 0.0],
    [1.0, 0.0, 1.0],
    [1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0],
    BLACK,
];

impl Card {
    fn new(width: usize, height: usize, square: usize) -> Card {
        let unit = width.min(height).max(1) as f32;
        let band_half_widths = std::array::from_fn(|i| {
            let edge = BAND_EDGES[i].abs().max(BAND_EDGES[i + 1].abs());
            (CIRCLE * CIRCLE - edge * edge).max(0.0).sqrt()
        });
        Card {
            width,
            height,
            unit,
            square,
            line: (square / 16).max(1),
            frame: (square / 4).max(1),
            half_w: width as f32 / 2.0 / unit,
            half_h: height as f32 / 2.0 / unit,
            band_half_widths,
        }
    }

    fn rgb(&self, x: usize, y: usize) -> [f32; 3] {
        let (w, h) = (self.width, self.height);
        // Castellated frame along the image border.
        if x < self.frame || y < self.frame || x + self.frame >= w || y + self.frame >= h {
            let white = (x / self.square + y / self.square) % 2 == 1;
            return if white { WHITE } else { BLACK };
        }
        // Card coordinates of the pixel centre: origin at the image centre, y down.
        let u = (x as f32 + 0.5) / self.unit - self.half_w;
        let v = (y as f32 + 0.5) / self.unit - self.half_h;
        let r = (u * u + v * v).sqrt();
        let base = if r < CIRCLE {
            self.inside(x, y, u, v)
        } else {
            self.outside(x, y, u, v)
        };
        // White rim of the central circle, 2 px wide.
        let rim = coverage((r - CIRCLE).abs() * self.unit - 1.0);
        mix(base, WHITE, rim)
    }

    /// Background, grid and corner marks.
    fn outside(&self, x: usize, y: usize, u: f32, v: f32) -> [f32; 3] {
        // Grid lines, one through the centre column and row.
        let on_grid = |p: usize, n: usize| {
            (p + self.square - (n / 2) % self.square) % self.square < self.line
        };
        let mut colour = if on_grid(x, self.width) || on_grid(y, self.height) {
            WHITE
        } else {
            GRAY
        };
        let mark_x = self.half_w - MARK_INSET;
        let mark_y = self.half_h - MARK_INSET;
        let (du, dv) = (u.abs() - mark_x, v.abs() - mark_y);
        let d = (du * du + dv * dv).sqrt();
        if d < MARK_RADIUS + 1.0 / self.unit {
            // Quadrants alternate; signs taken in the mark's own frame.
            let (su, sv) = (u - mark_x.copysign(u), v - mark_y.copysign(v));
            let quadrant = if (su < 0.0) != (sv < 0.0) {
                WHITE
            } else {
                BLACK
            };
            colour = mix(colour, quadrant, coverage((d - MARK_RADIUS) * self.unit));
        }
        colour
    }

    /// The bands inside the central circle.
    fn inside(&self, x: usize, y: usize, u: f32, v: f32) -> [f32; 3] {
        let band = BAND_EDGES
            .windows(2)
            .position(|e| v >= e[0] && v < e[1])
            .unwrap_or(0);
        let half = self.band_half_widths[band];
        match band {
            0 => self.slanted_bars(u - v * TAN_5_DEG, COS_5_DEG),
            8 => self.slanted_bars(u + v, std::f32::consts::FRAC_1_SQRT_2),
            _ if u.abs() >= half => GRAY,
            _ => {
                // Position across the band, 0 at the left end to 1 at the right.
                let t = (u + half) / (2.0 * half);
                let pick = |n: usize| ((t * n as f32) as usize).min(n - 1);
                match band {
                    1 => COLOUR_BARS[pick(COLOUR_BARS.len())],
                    2 => [pick(6) as f32 / 5.0; 3],
                    3 => grating(t, x),
                    4 => self.centre(x, y, u),
                    5 => grating(t, y),
                    6 => [t; 3],
                    _ => hue(t),
                }
            }
        }
    }

    /// Black|white halves with a mid-gray cross through the image centre (2 px wide for even
    /// sizes, 1 px for odd, so it is centred exactly).
    fn centre(&self, x: usize, y: usize, u: f32) -> [f32; 3] {
        let on_axis = |p: usize, n: usize| p + 1 >= n / 2 + n % 2 && p <= n / 2;
        if on_axis(x, self.width) || on_axis(y, self.height) {
            GRAY
        } else if u < 0.0 {
            BLACK
        } else {
            WHITE
        }
    }

    /// Black and white bars, each 0.05 card units of `s` wide, antialiased. `s` is a slanted
    /// coordinate whose edges lie `Δs · to_px` card units apart perpendicularly.
    fn slanted_bars(&self, s: f32, to_perpendicular: f32) -> [f32; 3] {
        const PERIOD: f32 = 0.1;
        let f = (s / PERIOD).rem_euclid(1.0);
        // Signed distance to the nearest edge in periods, positive inside white (f ≥ ½).
        let to_edge = if f < 0.5 {
            -f.min(0.5 - f)
        } else {
            (f - 0.5).min(1.0 - f)
        };
        [coverage(-to_edge * PERIOD * to_perpendicular * self.unit); 3]
    }
}

/// Line gratings: five groups across the band (t in 0..1) with the periods of [`GRATINGS`]
/// along pixel coordinate `p`, white lines on black, separated by mid-gray gaps.
fn grating(t: f32, p: usize) -> [f32; 3] {
    let groups = GRATINGS.len();
    let scaled = t * groups as f32;
    let group = (scaled as usize).min(groups - 1);
    let within = scaled - group as f32;
    if !(0.1..0.9).contains(&within) {
        return GRAY;
    }
    let period = GRATINGS[group];
    if p % period < period / 2 {
        WHITE
    } else {
        BLACK
    }
}

/// Fully saturated hue sweep: red → yellow → green → cyan → blue → magenta → red over t in 0..1
/// (HSV with S = V = 1).
fn hue(t: f32) -> [f32; 3] {
    let h = t.clamp(0.0, 1.0) * 6.0;
    let channel = |offset: f32| (((h + offset).rem_euclid(6.0) - 3.0).abs() - 1.0).clamp(0.0, 1.0);
    [channel(0.0), channel(4.0), channel(2.0)]
}

/// Fraction of a pixel covered by a shape whose signed edge distance at the pixel centre is
/// `d` px (negative inside): a box-filter approximation.
fn coverage(d: f32) -> f32 {
    (0.5 - d).clamp(0.0, 1.0)
}

fn mix(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    [0, 1, 2].map(|i| a[i] + (b[i] - a[i]) * t)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(kind: PatternKind, width: u32, height: u32) -> PatternParams {
        PatternParams {
            kind,
            width,
            height,
            ..PatternParams::default()
        }
    }

    fn run(p: PatternParams) -> Image {
        let op = Pattern::new(p).unwrap();
        let ctx = RunContext {
            node: "p".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&[], &[])).unwrap();
        match out.take("image") {
            Some(Value::Image(image)) => (*image).clone(),
            other => panic!("expected an image, got {other:?}"),
        }
    }

    fn u8_format(channels: Channels) -> PixelFormat {
        PixelFormat {
            channels,
            depth: Depth::U8,
        }
    }

    #[test]
    fn size_and_format_follow_the_params() {
        for kind in PatternKind::ALL {
            for (channels, pc) in [
                (Channels::Gray, PatternChannels::Gray),
                (Channels::Rgb, PatternChannels::Rgb),
                (Channels::Rgba, PatternChannels::Rgba),
            ] {
                for (depth, pd) in [
                    (Depth::U8, PatternDepth::U8),
                    (Depth::U16, PatternDepth::U16),
                    (Depth::F32, PatternDepth::F32),
                ] {
                    let img = run(PatternParams {
                        channels: pc,
                        depth: pd,
                        ..params(*kind, 37, 23)
                    });
                    assert_eq!((img.width(), img.height()), (37, 23));
                    assert_eq!(img.format(), PixelFormat { channels, depth });
                }
            }
        }
        let img = run(PatternParams::default());
        assert_eq!((img.width(), img.height()), (640, 480));
        assert_eq!(img.format(), u8_format(Channels::Rgb));
    }

    #[test]
    fn empty_and_single_pixel_images() {
        for kind in PatternKind::ALL {
            for (w, h) in [(0, 0), (0, 5), (5, 0)] {
                let img = run(params(*kind, w, h));
                assert_eq!((img.width(), img.height()), (w as usize, h as usize));
                assert!(img.is_empty());
            }
            let img = run(params(*kind, 1, 1));
            assert_eq!(img.as_u8().unwrap().len(), 3);
        }
    }

    #[test]
    fn checkerboard_values() {
        let img = render(
            Drawing::Checkerboard { square: 4 },
            16,
            8,
            u8_format(Channels::Gray),
        )
        .unwrap();
        let at = |x: usize, y: usize| img.as_u8().unwrap()[y * 16 + x];
        assert_eq!(at(0, 0), 0);
        assert_eq!(at(3, 3), 0);
        assert_eq!(at(4, 0), 255);
        assert_eq!(at(0, 4), 255);
        assert_eq!(at(4, 4), 0);
        assert_eq!(at(15, 7), 0);
        assert_eq!(at(11, 7), 255);
        let f = render(
            Drawing::Checkerboard { square: 3 },
            6,
            3,
            PixelFormat {
                channels: Channels::Rgba,
                depth: Depth::F32,
            },
        )
        .unwrap();
        let px = &f.as_f32().unwrap()[3 * 4..4 * 4];
        assert_eq!(px, [1.0, 1.0, 1.0, 1.0]);
    }

    #[test]
    fn noise_is_deterministic_and_seeded() {
        let noise = |seed, w, h| {
            render(Drawing::Noise { seed }, w, h, u8_format(Channels::Rgb))
                .unwrap()
                .into_data()
        };
        assert_eq!(noise(7, 64, 48), noise(7, 64, 48));
        assert_ne!(noise(7, 64, 48), noise(8, 64, 48));
        // The same in a 1-thread and a 3-thread pool.
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let one = pool(1).install(|| noise(3, 301, 97));
        let three = pool(3).install(|| noise(3, 301, 97));
        assert_eq!(one, three);
    }

    #[test]
    fn noise_is_uniform_and_gray_is_the_red_channel() {
        let rgb = render(
            Drawing::Noise { seed: 1 },
            256,
            256,
            u8_format(Channels::Rgb),
        )
        .unwrap();
        let samples = rgb.as_u8().unwrap();
        let mean = samples.iter().map(|&v| f64::from(v)).sum::<f64>() / samples.len() as f64;
        assert!((mean - 127.5).abs() < 1.0, "mean {mean}");
        let mut histogram = [0usize; 256];
        for &v in samples {
            histogram[v as usize] += 1;
        }
        // 768 expected per value; a uniform source stays well within ±25 %.
        assert!(histogram.iter().all(|&n| (576..=960).contains(&n)));
        let gray = render(
            Drawing::Noise { seed: 1 },
            256,
            256,
            u8_format(Channels::Gray),
        )
        .unwrap();
        let reds: Vec<u8> = samples.iter().step_by(3).copied().collect();
        assert_eq!(gray.as_u8().unwrap(), reds);
        let f = render(
            Drawing::Noise { seed: 1 },
            64,
            64,
            PixelFormat {
                channels: Channels::Gray,
                depth: Depth::F32,
            },
        )
        .unwrap();
        assert!(f.as_f32().unwrap().iter().all(|v| (0.0..1.0).contains(v)));
    }

    #[test]
    fn gradient_ramps() {
        let img = render(Drawing::Gradient, 256, 3, u8_format(Channels::Rgb)).unwrap();
        let data = img.as_u8().unwrap();
        for x in 0..256 {
            assert_eq!(data[x * 3], x as u8);
            assert_eq!(data[x * 3 + 1], x as u8);
            assert_eq!(data[x * 3 + 2], 0);
            assert_eq!(data[2 * 256 * 3 + x * 3 + 2], 255);
        }
        assert_eq!(data[256 * 3 + 2], 128);
        let gray = render(Drawing::Gradient, 5, 2, u8_format(Channels::Gray)).unwrap();
        assert_eq!(
            gray.as_u8().unwrap(),
            [0, 64, 128, 191, 255, 0, 64, 128, 191, 255]
        );
        let wide = render(
            Drawing::Gradient,
            1000,
            1,
            PixelFormat {
                channels: Channels::Gray,
                depth: Depth::U16,
            },
        )
        .unwrap();
        let w = wide.as_u16().unwrap();
        assert_eq!((w[0], w[999]), (0, 65535));
        assert!(w.windows(2).all(|p| p[0] <= p[1]));
    }

    fn star_image(spokes: u32, w: usize, h: usize) -> Vec<u8> {
        render(
            Drawing::SiemensStar { spokes },
            w,
            h,
            u8_format(Channels::Gray),
        )
        .unwrap()
        .as_u8()
        .unwrap()
        .to_vec()
    }

    #[test]
    fn siemens_star_is_balanced_and_symmetric() {
        let (w, h) = (200, 160);
        let radius = 0.45 * 160.0;
        for spokes in [2, 7, 36, 200] {
            let img = star_image(spokes, w, h);
            let at = |x: usize, y: usize| i32::from(img[y * w + x]);
            let (mut sum, mut n) = (0.0, 0.0);
            for y in 0..h {
                for x in 0..w {
                    let (dx, dy) = (x as f64 + 0.5 - 100.0, y as f64 + 0.5 - 80.0);
                    let r = dx.hypot(dy);
                    if r < radius - 1.0 {
                        sum += f64::from(at(x, y));
                        n += 1.0;
                    }
                    if r > radius + 1.0 {
                        assert_eq!(at(x, y), 128);
                    }
                    // Mirroring about the horizontal axis swaps black and white.
                    let mirrored = at(x, h - 1 - y);
                    assert!(
                        (at(x, y) + mirrored - 255).abs() <= 1 || r > radius - 1.0,
                        "{spokes} ({x},{y}) {} {}",
                        at(x, y),
                        mirrored
                    );
                    // With an even count a half turn maps sectors onto their own colour.
                    if spokes % 2 == 0 {
                        assert!((at(x, y) - at(w - 1 - x, h - 1 - y)).abs() <= 1);
                    }
                }
            }
            let mean = sum / n;
            assert!((mean - 127.5).abs() < 2.0, "spokes {spokes}: mean {mean}");
        }
    }

    #[test]
    fn siemens_star_has_both_extremes_and_antialiased_edges() {
        let img = star_image(36, 300, 300);
        assert!(img.contains(&0) && img.contains(&255));
        let intermediate = img
            .iter()
            .filter(|&&v| v != 0 && v != 255 && v != 128)
            .count();
        assert!(intermediate > 1000, "{intermediate}");
    }

    #[test]
    fn test_card_is_rich() {
        let img = render(
            Drawing::TestCard { square: 32 },
            640,
            480,
            u8_format(Channels::Rgb),
        )
        .unwrap();
        let data = img.as_u8().unwrap();
        assert!(data.contains(&0) && data.contains(&255));
        let mut distinct = std::collections::BTreeSet::new();
        for p in data.chunks_exact(3) {
            distinct.insert([p[0], p[1], p[2]]);
        }
        // Colour bars, steps, ramps, hue sweep and antialiased edges give many colours.
        assert!(distinct.len() > 500, "{}", distinct.len());
        for bar in COLOUR_BARS {
            let bar = bar.map(|c| c as u8 * 255);
            assert!(distinct.contains(&bar), "missing bar {bar:?}");
        }
        let gray = render(
            Drawing::TestCard { square: 32 },
            640,
            480,
            u8_format(Channels::Gray),
        )
        .unwrap();
        for step in [0u8, 51, 102, 153, 204, 255] {
            assert!(gray.as_u8().unwrap().contains(&step), "missing step {step}");
        }
    }

    #[test]
    fn test_card_layout_is_resolution_independent() {
        // The same relative point lands on the same element at two sizes.
        let probe = |w: usize, h: usize, fx: f32, fy: f32| {
            let img = render(
                Drawing::TestCard { square: 32 },
                w,
                h,
                u8_format(Channels::Rgb),
            )
            .unwrap();
            let (x, y) = ((fx * w as f32) as usize, (fy * h as f32) as usize);
            let i = (y * w + x) * 3;
            img.as_u8().unwrap()[i..i + 3].to_vec()
        };
        // Colour bars, gray steps, the centre halves.
        for (fx, fy) in [(0.4, 0.24), (0.6, 0.32), (0.45, 0.51), (0.55, 0.49)] {
            assert_eq!(probe(640, 640, fx, fy), probe(1280, 1280, fx, fy));
        }
        // Centre band: black left of centre, white right of it.
        assert_eq!(probe(400, 300, 0.4, 0.51), [0, 0, 0]);
        assert_eq!(probe(400, 300, 0.6, 0.51), [255, 255, 255]);
    }

    #[test]
    fn test_card_depths_agree() {
        let fmt = |depth| PixelFormat {
            channels: Channels::Rgb,
            depth,
        };
        let draw = Drawing::TestCard { square: 16 };
        let a = render(draw, 320, 200, fmt(Depth::U8)).unwrap();
        let b = render(draw, 320, 200, fmt(Depth::F32)).unwrap();
        let c = render(draw, 320, 200, fmt(Depth::U16)).unwrap();
        for ((&u, &f), &s) in a
            .as_u8()
            .unwrap()
            .iter()
            .zip(b.as_f32().unwrap())
            .zip(c.as_u16().unwrap())
        {
            assert_eq!(u, (f * 255.0 + 0.5) as u8);
            assert_eq!(s, (f * 65535.0 + 0.5) as u16);
        }
    }

    #[test]
    fn render_is_thread_count_independent() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        for drawing in [
            Drawing::TestCard { square: 20 },
            Drawing::SiemensStar { spokes: 36 },
            Drawing::Gradient,
        ] {
            let draw = || render(drawing, 333, 211, u8_format(Channels::Rgb)).unwrap();
            assert_eq!(pool(1).install(draw), pool(3).install(draw));
        }
    }

    #[test]
    fn unused_params_must_keep_their_defaults() {
        let err = |p: PatternParams| Pattern::new(p).unwrap_err();
        let e = err(PatternParams {
            spokes: 12,
            ..params(PatternKind::Noise, 8, 8)
        });
        assert!(
            e.contains("`spokes` applies only to kind \"siemens_star\""),
            "{e}"
        );
        let e = err(PatternParams {
            square: 8,
            ..params(PatternKind::SiemensStar, 8, 8)
        });
        assert!(e.contains("`square` applies only to kinds"), "{e}");
        let e = err(PatternParams {
            seed: 1,
            ..params(PatternKind::TestCard, 8, 8)
        });
        assert!(e.contains("`seed` applies only to kind \"noise\""), "{e}");
        // Used ones may change.
        assert!(
            Pattern::new(PatternParams {
                seed: 5,
                ..params(PatternKind::Noise, 8, 8)
            })
            .is_ok()
        );
        assert!(
            Pattern::new(PatternParams {
                square: 5,
                ..params(PatternKind::TestCard, 8, 8)
            })
            .is_ok()
        );
        assert!(
            Pattern::new(PatternParams {
                spokes: 5,
                ..params(PatternKind::SiemensStar, 8, 8)
            })
            .is_ok()
        );
    }

    #[test]
    fn size_limits() {
        assert!(Pattern::new(params(PatternKind::Gradient, 32768, 8192)).is_ok());
        let e = Pattern::new(params(PatternKind::Gradient, 32768, 8193)).unwrap_err();
        assert!(e.contains("2^28"), "{e}");
        assert!(Pattern::new(params(PatternKind::Gradient, 32769, 1)).is_err());
        assert!(
            Pattern::new(PatternParams {
                square: 0,
                ..params(PatternKind::Checkerboard, 8, 8)
            })
            .is_err()
        );
        assert!(
            Pattern::new(PatternParams {
                spokes: 1,
                ..params(PatternKind::SiemensStar, 8, 8)
            })
            .is_err()
        );
    }

    #[test]
    fn schema_has_units_and_ranges() {
        use ocellus_engine::params::Params;
        let schema = PatternParams::schema();
        let width = schema.iter().find(|s| s.name == "width").unwrap();
        assert_eq!(
            (width.min, width.max, width.unit.as_str()),
            (Some(0.0), Some(32768.0), "px")
        );
        let spokes = schema.iter().find(|s| s.name == "spokes").unwrap();
        assert_eq!((spokes.min, spokes.max), (Some(2.0), Some(720.0)));
    }
}
