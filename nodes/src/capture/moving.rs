//! `capture.moving_shapes`: a generated video with ground truth — bright squares, flat or
//! textured, moving over a static textured background, with sensor noise — for testing
//! background subtraction, tracking and segmentation without data; and `capture.select`, which
//! picks one frame of a sequence.
//!
//! Every sample is a pure function of the frame number, its coordinates and the seed, so the
//! sequence is the same at any thread count. Frames are rendered one at a time by
//! [`render_frame`] (memory independent of the sequence length, rows in parallel);
//! [`moving_shapes`] is a loop over it.

use std::sync::Arc;

use ocellus_engine::op::{
    FrameSource, Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext,
};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Matrix, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::pattern::{PatternChannels, splitmix64};

/// Largest width or height of a generated frame.
pub const MAX_SIDE: u32 = 4096;

/// Most frames in one sequence.
pub const MAX_FRAMES: u32 = 10_000;

/// Rows per parallel task of [`render_frame`] (fixed, so the work split does not depend on the
/// thread count; every pixel is computed independently anyway).
const ROWS_PER_TASK: usize = 16;

param_enum! {
    /// Surface of the moving squares of `capture.moving_shapes`. Textures are fixed to the
    /// object: they move with it, subpixel motion included.
    pub enum MovingTexture {
        /// Uniform: every covered pixel is the square's level (220, 214, 205 in red, green,
        /// blue; 220 in gray).
        Flat = "flat",
        /// A checkerboard of 8 px cells, levels 170 and 250, with a seeded phase per square.
        Checker = "checker",
        /// Smooth value noise, unique per square: bilinear interpolation of a hashed lattice
        /// of 6 px cells, levels 150–250.
        Noise = "noise",
    }
}

params! {
    /// Parameters of `capture.moving_shapes`.
    pub struct MovingShapesParams {
        /// Frame width.
        width: u32 = 160 => [min = 1, max = 4096, unit = "px"],
        /// Frame height.
        height: u32 = 120 => [min = 1, max = 4096, unit = "px"],
        /// Number of frames.
        frames: u32 = 40 => [min = 1, max = 10000],
        /// Frame rate, sets each frame's timestamp (frame t at t / fps s).
        fps: f64 = 30.0 => [min = 0.001, max = 10000.0, unit = "frames/s"],
        /// Number of moving squares.
        shapes: u32 = 2 => [min = 0, max = 64],
        /// Side of each square.
        size_px: u32 = 16 => [min = 1, max = 4096, unit = "px"],
        /// Surface of the squares: "flat" (uniform), "checker" (8 px checkerboard, levels 170
        /// and 250) or "noise" (smooth value noise of 6 px cells, levels 150–250, unique per
        /// square); textures move with their square.
        texture: MovingTexture = MovingTexture::Flat,
        /// Speed of each square (its direction comes from the seed); squares bounce off the
        /// frame's edges.
        speed_px: f64 = 2.5 => [min = 0.0, max = 1000.0, unit = "px/frame"],
        /// Standard deviation of the Gaussian sensor noise added to every sample, 8-bit levels.
        noise_sigma: f64 = 4.0 => [min = 0.0, max = 100.0, unit = "levels"],
        /// Channel layout: "gray", "rgb" or "rgba" (alpha opaque).
        channels: PatternChannels = PatternChannels::Gray,
        /// Seed of the squares' start positions, directions and textures, and of the noise.
        seed: u64 = 0,
    }
}

/// The scene of [`moving_shapes`] and [`render_frame`].
#[derive(Debug, Clone, PartialEq)]
pub struct MovingScene {
    /// Frame width, px.
    pub width: usize,
    /// Frame height, px.
    pub height: usize,
    /// Frames.
    pub frames: usize,
    /// Frame rate, frames per second: frame `t` is at `t / fps` seconds
    /// ([`MovingScene::timestamp`]). It does not change the pixels.
    pub fps: f64,
    /// Moving squares.
    pub shapes: usize,
    /// Square side, px.
    pub size_px: usize,
    /// Surface of the squares.
    pub texture: MovingTexture,
    /// Speed, px per frame.
    pub speed_px: f64,
    /// Noise standard deviation, 8-bit levels.
    pub noise_sigma: f64,
    /// Output channels.
    pub channels: Channels,
    /// Seed.
    pub seed: u64,
}

/// Where square `s` starts and how it moves (from [`MovingScene::starts`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SquareStart {
    /// Top-left corner at frame 0, px: `[x, y]`, inside `[0, width − size] × [0, height − size]`.
    pub origin: [f64; 2],
    /// Velocity before bouncing, px per frame: `[vx, vy]`, of length `speed_px`.
    pub velocity: [f64; 2],
}

/// One rendered frame and its ground truth ([`render_frame`]).
#[derive(Debug, Clone, PartialEq)]
pub struct MovingFrame {
    /// The frame, u8 in the scene's channels.
    pub frame: Image,
    /// u8 gray: 255 where a square covers the pixel centre, else 0.
    pub mask: Image,
    /// u8 gray: 0 for background, `s + 1` where square `s` is the visible (topmost) square.
    /// Squares are drawn in index order, so where they overlap the highest index is on top.
    pub labels: Image,
    /// Top-left corner `[x, y]` of each square at this frame, px, continuous (the square covers
    /// the pixels whose centres lie in `[x, x + size) × [y, y + size)`).
    pub positions: Vec<[f64; 2]>,
}

/// A uniform value in [0, 1) from a hash.
fn unit(h: u64) -> f64 {
    (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// A standard normal value from two hashes (Box–Muller).
fn normal(a: u64, b: u64) -> f64 {
    let u = 1.0 - unit(a);
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * unit(b)).cos()
}

/// Position along one axis of a point bouncing between 0 and `range` (a triangle wave).
fn bounce(start: f64, travel: f64, range: f64) -> f64 {
    if range <= 0.0 {
        return 0.0;
    }
    let period = 2.0 * range;
    let p = (start + travel).rem_euclid(period);
    if p <= range { p } else { period - p }
}

/// Brightness of the flat squares, 8-bit levels (per channel: white-ish, slightly warm).
const SQUARE_LEVELS: [f64; 4] = [220.0, 214.0, 205.0, 255.0];

/// Per-channel factor of textured squares (the flat squares' warm tint, gray/red exactly 1).
const TEXTURE_TINT: [f64; 3] = [1.0, 214.0 / 220.0, 205.0 / 220.0];

/// Checkerboard cell side of texture "checker", px.
const CHECKER_CELL: i64 = 8;

/// Levels of the two checker cells.
const CHECKER_LEVELS: [f64; 2] = [250.0, 170.0];

/// Lattice spacing of texture "noise", px.
const NOISE_CELL: f64 = 6.0;

/// Darkest level and range of texture "noise".
const NOISE_LEVELS: (f64, f64) = (150.0, 100.0);

/// The texture of one square, a function of the object coordinate `(u, v)` (px from the
/// square's top-left corner).
#[derive(Debug, Clone, Copy)]
enum Surface {
    Flat,
    /// Checker with its cell phase, px.
    Checker([i64; 2]),
    /// Value noise with its lattice seed.
    Noise(u64),
}

impl Surface {
    /// The checker's texel `(i, j)`: texel centres are at object coordinates `(i + ½, j + ½)`.
    fn checker_texel(phase: [i64; 2], i: i64, j: i64) -> f64 {
        let cell =
            (i + phase[0]).div_euclid(CHECKER_CELL) + (j + phase[1]).div_euclid(CHECKER_CELL);
        CHECKER_LEVELS[cell.rem_euclid(2) as usize]
    }

    /// The value-noise lattice value at node `(a, b)`.
    fn noise_node(seed: u64, a: i64, b: i64) -> f64 {
        let key = (a as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ (b as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
        NOISE_LEVELS.0 + NOISE_LEVELS.1 * unit(splitmix64(seed ^ splitmix64(key)))
    }

    /// The texture level at object coordinate `(u, v)`, bilinearly interpolated so that it is
    /// continuous in `(u, v)` (subpixel motion shifts it smoothly). `Flat` is not sampled.
    fn sample(self, u: f64, v: f64) -> f64 {
        match self {
            Surface::Flat => SQUARE_LEVELS[0],
            Surface::Checker(phase) => {
                let (gu, gv) = (u - 0.5, v - 0.5);
                let (fi, fj) = (gu.floor(), gv.floor());
                let (fu, fv) = (gu - fi, gv - fj);
                let (i, j) = (fi as i64, fj as i64);
                let t = |di, dj| Surface::checker_texel(phase, i + di, j + dj);
                let top = t(0, 0) + fu * (t(1, 0) - t(0, 0));
                let bottom = t(0, 1) + fu * (t(1, 1) - t(0, 1));
                top + fv * (bottom - top)
            }
            Surface::Noise(seed) => {
                let (gu, gv) = (u / NOISE_CELL, v / NOISE_CELL);
                let (fa, fb) = (gu.floor(), gv.floor());
                let (fu, fv) = (gu - fa, gv - fb);
                let (a, b) = (fa as i64, fb as i64);
                let n = |da, db| Surface::noise_node(seed, a + da, b + db);
                let top = n(0, 0) + fu * (n(1, 0) - n(0, 0));
                let bottom = n(0, 1) + fu * (n(1, 1) - n(0, 1));
                top + fv * (bottom - top)
            }
        }
    }
}

impl MovingScene {
    /// The seed of every hash: `splitmix64(seed)`.
    fn hash_seed(&self) -> u64 {
        splitmix64(self.seed)
    }

    /// `hash(s, k)`: the `k`-th hash of square `s` (k < 8): 0, 1 start position, 2 direction,
    /// 3, 4 checker phase, 5 noise texture seed.
    fn square_hash(&self, s: usize, k: u64) -> u64 {
        splitmix64(self.hash_seed() ^ (s as u64 * 8 + k))
    }

    /// The bounce ranges `[width − size, height − size]`, px (0 where the square does not fit).
    fn ranges(&self) -> [f64; 2] {
        [
            self.width.saturating_sub(self.size_px) as f64,
            self.height.saturating_sub(self.size_px) as f64,
        ]
    }

    /// Start position and velocity of every square: square `s` starts at
    /// `(unit(hash(s, 0)) · (width − size), unit(hash(s, 1)) · (height − size))` and moves at
    /// `speed_px` in direction `2π · unit(hash(s, 2))`, where
    /// `hash(s, k) = splitmix64(splitmix64(seed) ^ (8s + k))`.
    ///
    /// This is the only per-scene data of the renderer: O(`shapes`) hashes, cheap enough that
    /// [`render_frame`] recomputes it for each frame (textures and background are analytic
    /// functions, nothing is tabulated per scene), so rendering frame `t` costs the same and
    /// needs the same memory whatever `t` and the sequence length are.
    pub fn starts(&self) -> Vec<SquareStart> {
        let [range_x, range_y] = self.ranges();
        (0..self.shapes)
            .map(|s| {
                let angle = std::f64::consts::TAU * unit(self.square_hash(s, 2));
                SquareStart {
                    origin: [
                        unit(self.square_hash(s, 0)) * range_x,
                        unit(self.square_hash(s, 1)) * range_y,
                    ],
                    velocity: [self.speed_px * angle.cos(), self.speed_px * angle.sin()],
                }
            })
            .collect()
    }

    /// Top-left corner `[x, y]` of every square at frame `t`, px: the bounce (triangle wave) of
    /// `origin + t · velocity` in `[0, width − size] × [0, height − size]`.
    pub fn positions(&self, t: usize) -> Vec<[f64; 2]> {
        let [range_x, range_y] = self.ranges();
        self.starts()
            .iter()
            .map(|start| {
                [
                    bounce(start.origin[0], start.velocity[0] * t as f64, range_x),
                    bounce(start.origin[1], start.velocity[1] * t as f64, range_y),
                ]
            })
            .collect()
    }

    /// Timestamp of frame `t`, seconds: `t / fps`.
    pub fn timestamp(&self, t: usize) -> f64 {
        t as f64 / self.fps
    }

    /// The surface of square `s`.
    fn surface(&self, s: usize) -> Surface {
        match self.texture {
            MovingTexture::Flat => Surface::Flat,
            MovingTexture::Checker => {
                let cell = CHECKER_CELL as u64;
                Surface::Checker([
                    (self.square_hash(s, 3) % cell) as i64,
                    (self.square_hash(s, 4) % cell) as i64,
                ])
            }
            MovingTexture::Noise => Surface::Noise(self.square_hash(s, 5)),
        }
    }

    /// Checks that the squares fit the frame and the labels.
    fn check(&self) -> Result<(), String> {
        if self.shapes > usize::from(u8::MAX) {
            return Err(format!(
                "{} squares do not fit the u8 labels (at most 255)",
                self.shapes
            ));
        }
        if self.size_px > self.width || self.size_px > self.height {
            return Err(format!(
                "squares of {} px do not fit a {}×{} frame",
                self.size_px, self.width, self.height
            ));
        }
        Ok(())
    }
}

/// Renders frame `t` (0-based, below `scene.frames`) alone, with its ground truth: see
/// [`MovingFrame`]. Memory and time do not depend on `t` or on the sequence length, and the
/// result is bit-identical to frame `t` of [`moving_shapes`] at any thread count.
///
/// Square `s`'s top-left corner at frame `t` is [`MovingScene::positions`]; it covers the
/// pixels whose centres `(x + ½, y + ½)` lie in `[x_s, x_s + size) × [y_s, y_s + size)`, and
/// squares are drawn in index order (the highest index on top). A covered pixel's level is the
/// square's texture at the object coordinate `(x + ½ − x_s, y + ½ − y_s)`:
/// - "flat": 220 (gray) or 220, 214, 205 (red, green, blue);
/// - "checker": the checkerboard of 8 px cells, levels 250 and 170, shifted by a seeded phase
///   of 0–7 px per axis and square (texels of 1 px at object coordinates `(i + ½, j + ½)`),
///   bilinearly interpolated at the object coordinate;
/// - "noise": value noise, the bilinear interpolation at `(u/6, v/6)` of a lattice of values
///   `150 + 100 · unit(hash)` hashed from the square's own seed and the node;
///
/// a textured level `L` is `L`, `L · 214/220`, `L · 205/220` in red, green, blue (gray is `L`).
/// Uncovered pixels show the static background (stripes and blobs, 40–130 levels). Sample `c`
/// of pixel `i = (t·height + y)·width + x` gets Gaussian noise of `noise_sigma` from the
/// Box–Muller transform of `splitmix64(k)` and `splitmix64(k ^ 0xA5A5)`,
/// `k = splitmix64(seed) ^ (8i + c)·0x2545F4914F6CDD1D` (none on alpha), then is rounded and
/// clamped to 0–255.
///
/// Rows are rendered in parallel in tasks of a fixed number of rows; per row only the squares
/// whose vertical extent covers it are visited, and per square only its horizontal span.
pub fn render_frame(scene: &MovingScene, t: usize) -> Result<MovingFrame, String> {
    scene.check()?;
    if t >= scene.frames {
        return Err(format!(
            "frame {t} is outside a sequence of {} frames",
            scene.frames
        ));
    }
    let positions = scene.positions(t);
    render_at(scene, t, positions)
}

/// Renders frame `t` (its noise) with the squares' top-left corners at `positions`.
fn render_at(
    scene: &MovingScene,
    t: usize,
    positions: Vec<[f64; 2]>,
) -> Result<MovingFrame, String> {
    let (w, h) = (scene.width, scene.height);
    let c = scene.channels.count();
    let size = scene.size_px as f64;
    let seed = scene.hash_seed();
    let surfaces: Vec<Surface> = (0..positions.len()).map(|s| scene.surface(s)).collect();
    let flat = scene.texture == MovingTexture::Flat;
    let color = c.min(3);
    // The background's column factor `cos(0.05x − phase)` per colour channel.
    let column_cos: Vec<Vec<f64>> = (0..color)
        .map(|ch| {
            let phase = ch as f64 * 0.9;
            (0..w).map(|x| (0.05 * x as f64 - phase).cos()).collect()
        })
        .collect();
    let mut frame = vec![0u8; w * h * c];
    let mut mask = vec![0u8; w * h];
    let mut labels = vec![0u8; w * h];
    let frame_base = t as u64 * h as u64;
    frame
        .par_chunks_mut((ROWS_PER_TASK * w * c).max(1))
        .zip(mask.par_chunks_mut((ROWS_PER_TASK * w).max(1)))
        .zip(labels.par_chunks_mut((ROWS_PER_TASK * w).max(1)))
        .enumerate()
        .for_each(|(task, ((frame_rows, mask_rows), label_rows))| {
            let mut level = vec![0.0f64; w];
            let rows = frame_rows
                .chunks_exact_mut((w * c).max(1))
                .zip(mask_rows.chunks_exact_mut(w.max(1)))
                .zip(label_rows.chunks_exact_mut(w.max(1)));
            for (r, ((frame_row, mask_row), label_row)) in rows.enumerate() {
                let y = task * ROWS_PER_TASK + r;
                let cy = y as f64 + 0.5;
                // Squares in index order: later ones overwrite earlier ones (on top).
                for (s, (&[bx, by], surface)) in positions.iter().zip(&surfaces).enumerate() {
                    if !(cy >= by && cy < by + size) {
                        continue;
                    }
                    let v = cy - by;
                    // Candidate columns with a margin; the exact test decides.
                    let lo = ((bx - 0.5).floor() - 1.0).max(0.0) as usize;
                    let hi = ((bx + size - 0.5).ceil() + 1.0).clamp(0.0, w as f64) as usize;
                    for x in lo..hi {
                        let cx = x as f64 + 0.5;
                        if cx >= bx && cx < bx + size {
                            label_row[x] = s as u8 + 1;
                            mask_row[x] = 255;
                            if !flat {
                                level[x] = surface.sample(cx - bx, v);
                            }
                        }
                    }
                }
                let yf = y as f64;
                let row_sin: Vec<f64> = (0..color)
                    .map(|ch| (0.043 * yf + 0.5 * (ch as f64 * 0.9)).sin())
                    .collect();
                let row_index = (frame_base + y as u64) * w as u64;
                for (x, px) in frame_row.chunks_exact_mut(c).enumerate() {
                    let covered = label_row[x] != 0;
                    let i = row_index + x as u64;
                    for (ch, out) in px.iter_mut().enumerate() {
                        let clean = if ch == 3 {
                            255.0
                        } else if covered {
                            if flat {
                                SQUARE_LEVELS[ch]
                            } else {
                                level[x] * TEXTURE_TINT[ch]
                            }
                        } else {
                            let xf = x as f64;
                            let phase = ch as f64 * 0.9;
                            let stripes = (0.11 * xf + 0.07 * yf + phase).sin();
                            let blobs = column_cos[ch][x] * row_sin[ch];
                            85.0 + 25.0 * stripes + 20.0 * blobs
                        };
                        let noise = if ch == 3 || scene.noise_sigma == 0.0 {
                            0.0
                        } else {
                            let k = seed ^ (i * 8 + ch as u64).wrapping_mul(0x2545_F491_4F6C_DD1D);
                            scene.noise_sigma * normal(splitmix64(k), splitmix64(k ^ 0xA5A5))
                        };
                        *out = (clean + noise).round().clamp(0.0, 255.0) as u8;
                    }
                }
            }
        });
    Ok(MovingFrame {
        frame: Image::from_u8(w, h, scene.channels, frame).map_err(|e| e.to_string())?,
        mask: Image::from_u8(w, h, Channels::Gray, mask).map_err(|e| e.to_string())?,
        labels: Image::from_u8(w, h, Channels::Gray, labels).map_err(|e| e.to_string())?,
        positions,
    })
}

/// Renders the sequence: `(frames, masks)`, frame `t` and mask `t` being those of
/// [`render_frame`]`(scene, t)` — the frames u8 in `scene.channels`, the masks u8 gray (255
/// where a square covers the pixel centre, else 0).
pub fn moving_shapes(scene: &MovingScene) -> Result<(Vec<Image>, Vec<Image>), String> {
    scene.check()?;
    let mut frames = Vec::with_capacity(scene.frames);
    let mut masks = Vec::with_capacity(scene.frames);
    for t in 0..scene.frames {
        let rendered = render_frame(scene, t)?;
        frames.push(rendered.frame);
        masks.push(rendered.mask);
    }
    Ok((frames, masks))
}

/// A generated moving-object sequence with ground truth (`capture.moving_shapes`).
#[derive(Debug, Clone, PartialEq)]
pub struct MovingShapes {
    scene: MovingScene,
}

impl MovingShapes {
    /// The scene this operator renders (for rendering frames one at a time with
    /// [`render_frame`]).
    pub fn scene(&self) -> &MovingScene {
        &self.scene
    }
}

impl Op for MovingShapes {
    type Params = MovingShapesParams;
    const ID: &'static str = "capture.moving_shapes";
    const SUMMARY: &'static str = "Generates a video of flat or textured squares moving over a textured background, with ground-truth masks, labels and positions.";
    const DOC: &'static str = r#"
Generates `frames` u8 frames of `shapes` bright squares (`size_px` side) moving at `speed_px`
per frame over a static background of smooth stripes and blobs (levels 40–130), bouncing off
the edges, plus Gaussian sensor noise of `noise_sigma` levels; and the ground truth per frame:
a mask (255 where a square covers the pixel centre), a label image and the squares' positions.

`texture` is the squares' surface, fixed to the object (it moves with its square):
- "flat": uniform, levels 220 (gray) or 220, 214, 205 (RGB);
- "checker": a checkerboard of 8 px cells, levels 170 and 250, with a seeded phase per square;
- "noise": smooth value noise, unique per square: a hashed lattice of 6 px cells, levels
  150–250, bilinearly interpolated.
A texture is sampled at the pixel centre minus the square's continuous top-left corner, with
bilinear interpolation, so subpixel motion moves it smoothly — a feature tracker (KLT) can be
scored against `positions`.

Outputs per frame: `labels` is u8 gray, 0 for background and s + 1 where square s is visible
(squares are drawn in index order, the highest index on top where they overlap); `positions`
is a `shapes` × 2 matrix of the squares' top-left corners (x, y), px, continuous: square s
covers the pixels whose centres lie in [x, x + size_px) × [y, y + size_px).

`fps` sets each frame's timestamp: frame t is at t / fps seconds; it does not change pixels.

Start positions, directions, texture phases and seeds, and the noise come from `seed` through
SplitMix64 (the noise by Box–Muller from hashes of the sample index), so the sequence is
reproducible and the same at any thread count; each frame is a pure function of its index and
can be rendered alone. The background never changes, so a background model learns it exactly;
the masks score a segmentation (`analyze.evaluate`, `analyze.roc`).

The moving-object test sequences of background-subtraction evaluations (e.g. the synthetic
videos of the changedetection.net and BMC benchmarks) are the model; value noise after Perlin
("An image synthesizer", SIGGRAPH 1985).

Example:
    "clip": (op: "capture.moving_shapes", params: (frames: 40, shapes: 2, seed: 7)),
    "track": (op: "capture.moving_shapes", params: (width: 640, height: 480, texture: "noise", size_px: 60)),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "frames",
                PortType::Image.list_of(),
                "The frames in time order, u8, `width` × `height`.",
            )
            .per_frame(),
            PortSpec::new(
                "masks",
                PortType::Image.list_of(),
                "Ground truth per frame: u8 gray, 255 where a square covers the pixel.",
            )
            .per_frame(),
            PortSpec::new(
                "labels",
                PortType::Image.list_of(),
                "Ground truth per frame: u8 gray, 0 for background, s + 1 where square s is on top.",
            )
            .per_frame(),
            PortSpec::new(
                "positions",
                PortType::Matrix.list_of(),
                "Ground truth per frame: `shapes` × 2 matrix of the squares' top-left corners (x, y), px.",
            )
            .per_frame(),
        ]
    }

    fn new(params: MovingShapesParams) -> Result<Self, String> {
        let MovingShapesParams {
            width,
            height,
            frames,
            fps,
            shapes,
            size_px,
            texture,
            speed_px,
            noise_sigma,
            channels,
            seed,
        } = params;
        if !speed_px.is_finite() || !noise_sigma.is_finite() {
            return Err("`speed_px` and `noise_sigma` must be finite".into());
        }
        if !(fps.is_finite() && fps > 0.0) {
            return Err(format!("`fps` must be finite and positive, got {fps}"));
        }
        if size_px > width || size_px > height {
            return Err(format!(
                "`size_px` {size_px} does not fit a {width}×{height} frame"
            ));
        }
        let channels = match channels {
            PatternChannels::Gray => Channels::Gray,
            PatternChannels::Rgb => Channels::Rgb,
            PatternChannels::Rgba => Channels::Rgba,
        };
        Ok(MovingShapes {
            scene: MovingScene {
                width: width as usize,
                height: height as usize,
                frames: frames as usize,
                fps,
                shapes: shapes as usize,
                size_px: size_px as usize,
                texture,
                speed_px,
                noise_sigma,
                channels,
                seed,
            },
        })
    }
}

/// The `shapes × 2` matrix of top-left corners.
fn positions_matrix(positions: &[[f64; 2]]) -> Result<Matrix, String> {
    let data = positions.iter().flat_map(|p| p.iter().copied()).collect();
    Matrix::new(positions.len(), 2, data).map_err(|e| e.to_string())
}

impl Operator for MovingShapes {
    fn run(&self, ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let n = self.scene.frames;
        let (mut frames, mut masks) = (Vec::with_capacity(n), Vec::with_capacity(n));
        let (mut labels, mut positions) = (Vec::with_capacity(n), Vec::with_capacity(n));
        let mut source = MovingSource {
            scene: self.scene.clone(),
        };
        for t in 0..n {
            let mut one = source.frame(ctx, t)?;
            let mut take = |name: &str| {
                one.take(name)
                    .ok_or_else(|| OpError::failed(format!("frame {t}: no `{name}`")))
            };
            frames.push(take("frames")?);
            masks.push(take("masks")?);
            labels.push(take("labels")?);
            positions.push(take("positions")?);
        }
        Ok(Outputs::new()
            .with("frames", Value::list(PortType::Image, frames))
            .with("masks", Value::list(PortType::Image, masks))
            .with("labels", Value::list(PortType::Image, labels))
            .with("positions", Value::list(PortType::Matrix, positions)))
    }

    fn frame_source(
        &self,
        _ctx: &RunContext,
        _inputs: &Inputs<'_>,
    ) -> Option<Result<Box<dyn FrameSource>, OpError>> {
        Some(self.scene.check().map_err(OpError::failed).map(|()| {
            Box::new(MovingSource {
                scene: self.scene.clone(),
            }) as Box<dyn FrameSource>
        }))
    }
}

/// `capture.moving_shapes` as a stream source: frame `t` rendered on demand by
/// [`render_frame`], so memory does not grow with the sequence length.
struct MovingSource {
    scene: MovingScene,
}

impl FrameSource for MovingSource {
    fn frames(&self) -> usize {
        self.scene.frames
    }

    fn timestamp_us(&self, index: usize) -> i64 {
        (self.scene.timestamp(index) * 1e6).round() as i64
    }

    fn frame(&mut self, _ctx: &RunContext, index: usize) -> Result<Outputs, OpError> {
        let rendered = render_frame(&self.scene, index).map_err(OpError::failed)?;
        let matrix = positions_matrix(&rendered.positions).map_err(OpError::failed)?;
        Ok(Outputs::new()
            .with("frames", Value::image(rendered.frame))
            .with("masks", Value::image(rendered.mask))
            .with("labels", Value::image(rendered.labels))
            .with("positions", Value::Matrix(Arc::new(matrix))))
    }
}

params! {
    /// Parameters of `capture.select`.
    pub struct SelectParams {
        /// Which frame: 0 is the first; negative counts from the end (−1 is the last).
        index: i64 = -1,
    }
}

/// Picks one frame of a sequence (`capture.select`).
#[derive(Debug, Clone, PartialEq)]
pub struct Select {
    index: i64,
}

/// The list position of `index` (negative from the end) in a list of `len`, if inside it.
pub fn resolve_index(index: i64, len: usize) -> Option<usize> {
    let len = i64::try_from(len).ok()?;
    let i = if index < 0 { len + index } else { index };
    if (0..len).contains(&i) {
        usize::try_from(i).ok()
    } else {
        None
    }
}

impl Op for Select {
    type Params = SelectParams;
    const ID: &'static str = "capture.select";
    const SUMMARY: &'static str = "Picks one frame of an image sequence by its index.";
    const DOC: &'static str = r#"
Outputs frame `index` of the `frames` list: 0 is the first, negative indices count from the end
(−1 is the last, as in Python). An index outside the list is an error naming the list's length.

Example:
    "last": (op: "capture.select", inputs: { "frames": "fg.masks" }, params: (index: -1)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "frames",
            PortType::Image.list_of(),
            "An image sequence.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "frame",
            PortType::Image,
            "The selected frame.",
        )]
    }

    fn new(params: SelectParams) -> Result<Self, String> {
        Ok(Select {
            index: params.index,
        })
    }
}

impl Operator for Select {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let Value::List(list) = inputs.require("frames")? else {
            return Err(OpError::input("frames", "expected a list of images"));
        };
        let Some(i) = resolve_index(self.index, list.items.len()) else {
            return Err(OpError::input(
                "frames",
                format!(
                    "index {} is outside a sequence of {} frames",
                    self.index,
                    list.items.len()
                ),
            ));
        };
        match list.items.get(i) {
            Some(frame @ Value::Image(_)) => Ok(Outputs::new().with("frame", frame.clone())),
            Some(other) => Err(OpError::input(
                "frames",
                format!("element {i} is a {}, not an Image", other.port_type()),
            )),
            None => Err(OpError::input("frames", "empty sequence")),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene() -> MovingScene {
        MovingScene {
            width: 64,
            height: 48,
            frames: 12,
            fps: 30.0,
            shapes: 1,
            size_px: 10,
            texture: MovingTexture::Flat,
            speed_px: 3.0,
            noise_sigma: 0.0,
            channels: Channels::Gray,
            seed: 3,
        }
    }

    fn u8s(image: &Image) -> &[u8] {
        image.as_u8().unwrap_or(&[])
    }

    /// The default scene of the operator.
    fn default_scene() -> MovingScene {
        MovingShapes::new(MovingShapesParams::default())
            .unwrap()
            .scene()
            .clone()
    }

    /// FNV-1a over the bytes of every frame, then every mask.
    fn fnv(frames: &[Image], masks: &[Image]) -> u64 {
        let mut h = 0xcbf2_9ce4_8422_2325u64;
        for image in frames.iter().chain(masks) {
            for &b in u8s(image) {
                h = (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
            }
        }
        h
    }

    #[test]
    fn one_square_covers_exactly_its_area_and_moves_at_its_speed() {
        let s = scene();
        let (frames, masks) = moving_shapes(&s).unwrap();
        assert_eq!((frames.len(), masks.len()), (12, 12));
        let centroid = |m: &Image| {
            let (mut sx, mut sy, mut n) = (0.0, 0.0, 0.0);
            for (i, &v) in u8s(m).iter().enumerate() {
                if v == 255 {
                    sx += (i % 64) as f64;
                    sy += (i / 64) as f64;
                    n += 1.0;
                }
            }
            (sx / n, sy / n, n)
        };
        for m in &masks {
            // A 10 px square covers 10×10 pixel centres (up to one row/column at the edges
            // of the half-open interval, never more).
            let (_, _, n) = centroid(m);
            assert!((81.0..=100.0).contains(&n), "area {n}");
        }
        // Away from bounces the centroid moves 3 px per frame (±1 px of rasterization).
        let steps: Vec<f64> = masks
            .windows(2)
            .map(|w| {
                let (a, b) = (centroid(&w[0]), centroid(&w[1]));
                ((a.0 - b.0).powi(2) + (a.1 - b.1).powi(2)).sqrt()
            })
            .collect();
        let straight = steps.iter().filter(|d| (**d - 3.0).abs() <= 1.0).count();
        assert!(straight >= 8, "steps {steps:?}");
        // Without noise, foreground pixels are the square's level and background is darker.
        for (f, m) in frames.iter().zip(&masks) {
            for (&v, &k) in u8s(f).iter().zip(u8s(m)) {
                if k == 255 {
                    assert_eq!(v, 220);
                } else {
                    assert!((40..=131).contains(&v), "background {v}");
                }
            }
        }
    }

    #[test]
    fn reproducible_and_seeded() {
        let mut s = scene();
        s.noise_sigma = 5.0;
        s.channels = Channels::Rgb;
        let a = moving_shapes(&s).unwrap();
        let b = moving_shapes(&s).unwrap();
        assert_eq!(a, b);
        s.seed = 4;
        let c = moving_shapes(&s).unwrap();
        assert_ne!(a.0, c.0);
        assert_eq!(a.0[0].channels(), Channels::Rgb);
    }

    #[test]
    fn noise_has_the_requested_spread() {
        let mut s = scene();
        s.shapes = 0;
        s.frames = 2;
        s.noise_sigma = 6.0;
        let (noisy, _) = moving_shapes(&s).unwrap();
        s.noise_sigma = 0.0;
        let (clean, _) = moving_shapes(&s).unwrap();
        let d: Vec<f64> = u8s(&noisy[1])
            .iter()
            .zip(u8s(&clean[1]))
            .map(|(&a, &b)| f64::from(a) - f64::from(b))
            .collect();
        let mean = d.iter().sum::<f64>() / d.len() as f64;
        let sd = (d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / d.len() as f64).sqrt();
        assert!(
            mean.abs() < 0.5 && (sd - 6.0).abs() < 0.6,
            "mean {mean} sd {sd}"
        );
    }

    #[test]
    fn squares_that_do_not_fit_are_rejected() {
        let mut s = scene();
        s.size_px = 49;
        assert!(moving_shapes(&s).is_err());
        assert!(render_frame(&s, 0).is_err());
        let params = MovingShapesParams {
            size_px: 500,
            ..MovingShapesParams::default()
        };
        assert!(MovingShapes::new(params).is_err());
        let params = MovingShapesParams {
            fps: 0.0,
            ..MovingShapesParams::default()
        };
        assert!(MovingShapes::new(params).is_err());
    }

    const CHK_DEFAULT: u64 = 0x8ade_6c20_c950_8259;
    const CHK_SEED7: u64 = 0x22b8_9584_d961_056b;
    const CHK_RGB3: u64 = 0x0182_52f8_2bcb_08e2;
    const CHK_RGBA5: u64 = 0xa885_ee7a_a7ec_7583;

    /// Checksums of the output before per-frame rendering and textures were added (computed
    /// on the previous implementation): the default "flat" output must stay bit-identical
    /// (`graphs/segment.ron` is the seed-7 scene).
    #[test]
    fn default_output_is_unchanged() {
        let base = default_scene();
        assert_eq!(base.texture, MovingTexture::Flat);
        let check = |scene: &MovingScene, expected: u64, name: &str| {
            let (f, m) = moving_shapes(scene).unwrap();
            assert_eq!(fnv(&f, &m), expected, "{name}: {:#018x}", fnv(&f, &m));
        };
        check(&base, CHK_DEFAULT, "default");
        let mut s7 = base.clone();
        s7.seed = 7;
        check(&s7, CHK_SEED7, "seed 7 (segment.ron)");
        let mut rgb = base.clone();
        rgb.channels = Channels::Rgb;
        rgb.shapes = 3;
        check(&rgb, CHK_RGB3, "rgb, 3 shapes");
        let mut rgba = base.clone();
        rgba.channels = Channels::Rgba;
        rgba.shapes = 5;
        rgba.seed = 11;
        rgba.speed_px = 7.3;
        check(&rgba, CHK_RGBA5, "rgba, 5 shapes, speed 7.3, seed 11");
    }

    #[test]
    fn render_frame_equals_the_sequence_frame() {
        for texture in MovingTexture::ALL.iter().copied() {
            let s = MovingScene {
                shapes: 3,
                channels: Channels::Rgb,
                noise_sigma: 3.0,
                texture,
                ..scene()
            };
            let (frames, masks) = moving_shapes(&s).unwrap();
            for t in [0, 5, 11] {
                let r = render_frame(&s, t).unwrap();
                assert_eq!(r.frame, frames[t], "{texture:?} frame {t}");
                assert_eq!(r.mask, masks[t], "{texture:?} mask {t}");
                assert_eq!(r.positions, s.positions(t));
                assert_eq!(r.positions.len(), 3);
                let again = render_frame(&s, t).unwrap();
                assert_eq!(again, r);
            }
            assert!(render_frame(&s, 12).is_err());
        }
    }

    #[test]
    fn the_same_at_any_thread_count() {
        let s = MovingScene {
            width: 97,
            height: 83,
            shapes: 5,
            size_px: 17,
            texture: MovingTexture::Noise,
            noise_sigma: 4.0,
            channels: Channels::Rgba,
            ..scene()
        };
        let with = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| render_frame(&s, 7).unwrap())
        };
        let one = with(1);
        assert_eq!(one, with(3));
        assert_eq!(one, with(8));
    }

    #[test]
    fn labels_agree_with_masks_and_the_last_square_is_on_top() {
        let s = MovingScene {
            shapes: 8,
            size_px: 14,
            texture: MovingTexture::Checker,
            ..scene()
        };
        let mut overlaps = 0;
        for t in 0..s.frames {
            let r = render_frame(&s, t).unwrap();
            let (mask, labels) = (u8s(&r.mask), u8s(&r.labels));
            for (i, (&m, &l)) in mask.iter().zip(labels).enumerate() {
                assert_eq!(m == 255, l > 0, "pixel {i}");
                assert!(m == 0 || m == 255);
                let (cx, cy) = ((i % s.width) as f64 + 0.5, (i / s.width) as f64 + 0.5);
                let size = s.size_px as f64;
                let covering: Vec<usize> = (0..s.shapes)
                    .filter(|&k| {
                        let [bx, by] = r.positions[k];
                        cx >= bx && cx < bx + size && cy >= by && cy < by + size
                    })
                    .collect();
                overlaps += usize::from(covering.len() > 1);
                assert_eq!(covering.last().map_or(0, |&k| k + 1), usize::from(l));
            }
        }
        assert!(overlaps > 0, "the scene should have overlapping squares");
    }

    #[test]
    fn positions_bounce_inside_the_frame() {
        let s = MovingScene {
            frames: 400,
            shapes: 6,
            speed_px: 7.3,
            ..scene()
        };
        let max = [(s.width - s.size_px) as f64, (s.height - s.size_px) as f64];
        let mut previous: Option<Vec<[f64; 2]>> = None;
        let mut bounces = 0;
        for t in 0..s.frames {
            let p = s.positions(t);
            for q in &p {
                for a in 0..2 {
                    assert!((0.0..=max[a]).contains(&q[a]), "frame {t}: {q:?}");
                }
            }
            if let Some(prev) = &previous {
                for (a, b) in prev.iter().zip(&p) {
                    let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt();
                    assert!(d <= 7.3 + 1e-9, "step {d}");
                    bounces += usize::from(d < 7.3 - 1e-6);
                }
            }
            previous = Some(p);
        }
        assert!(bounces > 10, "bounces {bounces}");
        assert_eq!(s.positions(0).len(), 6);
        let starts = s.starts();
        for (start, p) in starts.iter().zip(s.positions(0)) {
            assert_eq!(start.origin, p);
            let v = start.velocity;
            assert!(((v[0].powi(2) + v[1].powi(2)).sqrt() - 7.3).abs() < 1e-9);
        }
    }

    /// A textured, noise-free one-square scene.
    fn textured(texture: MovingTexture, channels: Channels) -> MovingScene {
        MovingScene {
            size_px: 24,
            texture,
            channels,
            ..scene()
        }
    }

    #[test]
    fn textures_move_with_the_object_by_whole_pixels() {
        for texture in [MovingTexture::Checker, MovingTexture::Noise] {
            for channels in [Channels::Gray, Channels::Rgb] {
                let s = textured(texture, channels);
                let c = channels.count();
                let a = render_at(&s, 0, vec![[10.25, 7.5]]).unwrap();
                let b = render_at(&s, 1, vec![[13.25, 9.5]]).unwrap();
                let (fa, fb) = (u8s(&a.frame), u8s(&b.frame));
                let (la, lb) = (u8s(&a.labels), u8s(&b.labels));
                let (mut lo, mut hi, mut n) = (255u8, 0u8, 0);
                for y in 0..s.height - 2 {
                    for x in 0..s.width - 3 {
                        let (i, j) = (y * s.width + x, (y + 2) * s.width + x + 3);
                        if la[i] != 1 {
                            continue;
                        }
                        assert_eq!(lb[j], 1);
                        for ch in 0..c {
                            assert_eq!(fa[i * c + ch], fb[j * c + ch], "{texture:?} ({x}, {y})");
                            lo = lo.min(fa[i * c + ch]);
                            hi = hi.max(fa[i * c + ch]);
                        }
                        n += 1;
                    }
                }
                assert_eq!(n, 24 * 24);
                assert!(hi - lo > 40, "{texture:?}: levels {lo}..{hi}");
                assert!(
                    lo >= 140,
                    "{texture:?}: foreground brighter than background"
                );
            }
        }
    }

    #[test]
    fn subpixel_motion_moves_the_texture_continuously() {
        for (texture, contrast) in [
            (MovingTexture::Checker, 80.0),
            (MovingTexture::Noise, 100.0),
        ] {
            let s = textured(texture, Channels::Gray);
            let base = [10.25, 7.5];
            let render = |d: f64| render_at(&s, 0, vec![[base[0] + d, base[1] + d]]).unwrap();
            let reference = render(0.0);
            let fr = u8s(&reference.frame);
            // Interior pixels (covered in both frames), compared at the same place.
            for d in [0.125, 0.25, 0.5] {
                let moved = render(d);
                let (fm, lm) = (u8s(&moved.frame), u8s(&moved.labels));
                let (mut max, mut sum, mut n) = (0.0f64, 0.0, 0.0);
                for (i, (&l0, &l1)) in u8s(&reference.labels).iter().zip(lm).enumerate() {
                    if l0 == 1 && l1 == 1 {
                        let diff = (f64::from(fr[i]) - f64::from(fm[i])).abs();
                        max = max.max(diff);
                        sum += diff;
                        n += 1.0;
                    }
                }
                let mean = sum / n;
                // Bilinear texels: a shift of d along both axes changes a pixel by at most
                // 2·d of the local step (plus rounding); nearest-texel sampling would jump by
                // the full contrast.
                assert!(
                    max <= 2.0 * d * contrast + 1.0,
                    "{texture:?} d {d}: max {max}"
                );
                assert!(
                    mean <= 0.5 * d * contrast + 1.0,
                    "{texture:?} d {d}: mean {mean}"
                );
                assert!(mean > 0.0, "{texture:?} d {d}: the texture must move");
            }
        }
    }

    #[test]
    fn tiny_frames_and_no_shapes_do_not_panic() {
        for texture in MovingTexture::ALL.iter().copied() {
            for channels in [Channels::Gray, Channels::Rgba] {
                let s = MovingScene {
                    width: 1,
                    height: 1,
                    frames: 3,
                    shapes: 3,
                    size_px: 1,
                    texture,
                    channels,
                    noise_sigma: 2.0,
                    ..scene()
                };
                let (frames, masks) = moving_shapes(&s).unwrap();
                assert_eq!(frames.len(), 3);
                assert_eq!(u8s(&masks[2]), &[255]);
                let r = render_frame(&s, 2).unwrap();
                assert_eq!(u8s(&r.labels), &[3]);
                assert_eq!(r.positions, vec![[0.0, 0.0]; 3]);
                let none = MovingScene { shapes: 0, ..s };
                let r = render_frame(&none, 0).unwrap();
                assert!(r.positions.is_empty());
                assert_eq!(u8s(&r.mask), &[0]);
                assert_eq!(positions_matrix(&r.positions).unwrap().rows, 0);
            }
        }
        let too_big = MovingScene {
            width: 1,
            height: 1,
            ..scene()
        };
        assert!(render_frame(&too_big, 0).is_err());
    }

    #[test]
    fn operator_declares_labels_positions_texture_and_fps() {
        let names: Vec<String> = MovingShapes::outputs()
            .iter()
            .map(|p| p.name.to_string())
            .collect();
        assert_eq!(names, ["frames", "masks", "labels", "positions"]);
        let s = default_scene();
        assert_eq!(s.fps, 30.0);
        assert!((s.timestamp(3) - 0.1).abs() < 1e-15);
        let params = MovingShapesParams {
            texture: MovingTexture::Noise,
            fps: 25.0,
            shapes: 4,
            ..MovingShapesParams::default()
        };
        let op = MovingShapes::new(params).unwrap();
        assert_eq!(op.scene().texture, MovingTexture::Noise);
        assert_eq!(op.scene().timestamp(50), 2.0);
        let r = render_frame(op.scene(), 3).unwrap();
        let m = positions_matrix(&r.positions).unwrap();
        assert_eq!((m.rows, m.cols), (4, 2));
        assert_eq!(m.get(2, 1), Some(r.positions[2][1]));
        let schema = <MovingShapesParams as ocellus_engine::params::Params>::schema();
        assert!(schema.iter().any(|p| p.name == "texture"));
        assert!(schema.iter().any(|p| p.name == "fps"));
    }

    #[test]
    fn stream_source_frames_equal_the_batch_lists() {
        let params = MovingShapesParams {
            frames: 5,
            shapes: 3,
            texture: MovingTexture::Checker,
            fps: 25.0,
            ..MovingShapesParams::default()
        };
        let op = MovingShapes::new(params).unwrap();
        let ctx = RunContext {
            node: "clip".into(),
            threads: 1,
            element: None,
        };
        let none = Inputs::new(&[], &[]);
        let mut source = op.frame_source(&ctx, &none).unwrap().unwrap();
        assert_eq!(source.frames(), 5);
        assert_eq!(
            (0..3).map(|k| source.timestamp_us(k)).collect::<Vec<_>>(),
            [0, 40_000, 80_000]
        );
        let mut batch = op.run(&ctx, &none).unwrap();
        for name in ["frames", "masks", "labels", "positions"] {
            let Some(Value::List(list)) = batch.take(name) else {
                panic!("no list {name}");
            };
            assert_eq!(list.items.len(), 5);
            for (k, item) in list.items.iter().enumerate() {
                let mut one = source.frame(&ctx, k).unwrap();
                assert_eq!(one.take(name).as_ref(), Some(item), "{name} {k}");
            }
        }
        assert!(source.frame(&ctx, 5).is_err());
        for p in MovingShapes::outputs() {
            assert!(p.per_frame, "{} is per frame", p.name);
        }
    }

    /// Time of one 1280×720 frame with 6 textured squares of 120 px (printed; run with
    /// `--nocapture`).
    #[test]
    fn frame_time_1280x720() {
        for (texture, channels) in [
            (MovingTexture::Noise, Channels::Gray),
            (MovingTexture::Checker, Channels::Gray),
            (MovingTexture::Noise, Channels::Rgb),
        ] {
            let s = MovingScene {
                width: 1280,
                height: 720,
                frames: 100,
                fps: 30.0,
                shapes: 6,
                size_px: 120,
                texture,
                speed_px: 2.5,
                noise_sigma: 4.0,
                channels,
                seed: 1,
            };
            let _warm = render_frame(&s, 0).unwrap();
            let runs = 8;
            let start = std::time::Instant::now();
            for t in 1..=runs {
                let r = render_frame(&s, t).unwrap();
                assert_eq!(r.frame.width(), 1280);
            }
            let ms = start.elapsed().as_secs_f64() * 1000.0 / runs as f64;
            println!(
                "moving_shapes 1280x720 {} {:?}, 6 squares of 120 px: {ms:.2} ms/frame ({} threads)",
                texture.name(),
                channels,
                rayon::current_num_threads()
            );
        }
    }

    #[test]
    fn select_resolves_positive_and_negative_indices() {
        assert_eq!(resolve_index(0, 3), Some(0));
        assert_eq!(resolve_index(2, 3), Some(2));
        assert_eq!(resolve_index(-1, 3), Some(2));
        assert_eq!(resolve_index(-3, 3), Some(0));
        assert_eq!(resolve_index(3, 3), None);
        assert_eq!(resolve_index(-4, 3), None);
        assert_eq!(resolve_index(-1, 0), None);
    }
}
