//! `capture.moving_shapes`: a generated video with ground truth — bright squares moving over a
//! static textured background, with sensor noise — for testing background subtraction,
//! tracking and segmentation without data; and `capture.select`, which picks one frame of a
//! sequence.
//!
//! Every sample is a pure function of the frame number, its coordinates and the seed, so the
//! sequence is the same at any thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Value};

use super::pattern::{PatternChannels, splitmix64};

/// Largest width or height of a generated frame.
pub const MAX_SIDE: u32 = 4096;

/// Most frames in one sequence.
pub const MAX_FRAMES: u32 = 10_000;

params! {
    /// Parameters of `capture.moving_shapes`.
    pub struct MovingShapesParams {
        /// Frame width.
        width: u32 = 160 => [min = 1, max = 4096, unit = "px"],
        /// Frame height.
        height: u32 = 120 => [min = 1, max = 4096, unit = "px"],
        /// Number of frames.
        frames: u32 = 40 => [min = 1, max = 10000],
        /// Number of moving squares.
        shapes: u32 = 2 => [min = 0, max = 64],
        /// Side of each square.
        size_px: u32 = 16 => [min = 1, max = 4096, unit = "px"],
        /// Speed of each square (its direction comes from the seed); squares bounce off the
        /// frame's edges.
        speed_px: f64 = 2.5 => [min = 0.0, max = 1000.0, unit = "px/frame"],
        /// Standard deviation of the Gaussian sensor noise added to every sample, 8-bit levels.
        noise_sigma: f64 = 4.0 => [min = 0.0, max = 100.0, unit = "levels"],
        /// Channel layout: "gray", "rgb" or "rgba" (alpha opaque).
        channels: PatternChannels = PatternChannels::Gray,
        /// Seed of the squares' start positions and directions, and of the noise.
        seed: u64 = 0,
    }
}

/// The scene of [`moving_shapes`].
#[derive(Debug, Clone, PartialEq)]
pub struct MovingScene {
    /// Frame width, px.
    pub width: usize,
    /// Frame height, px.
    pub height: usize,
    /// Frames.
    pub frames: usize,
    /// Moving squares.
    pub shapes: usize,
    /// Square side, px.
    pub size_px: usize,
    /// Speed, px per frame.
    pub speed_px: f64,
    /// Noise standard deviation, 8-bit levels.
    pub noise_sigma: f64,
    /// Output channels.
    pub channels: Channels,
    /// Seed.
    pub seed: u64,
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

/// The static background at `(x, y)`, channel `c`: smooth diagonal stripes and blobs between
/// 40 and 130 levels (the squares are 220, so foreground is always brighter).
fn background(x: f64, y: f64, c: usize) -> f64 {
    let phase = c as f64 * 0.9;
    let stripes = (0.11 * x + 0.07 * y + phase).sin();
    let blobs = (0.05 * x - phase).cos() * (0.043 * y + 0.5 * phase).sin();
    85.0 + 25.0 * stripes + 20.0 * blobs
}

/// Brightness of the squares, 8-bit levels (per channel: white-ish, slightly warm).
const SQUARE_LEVELS: [f64; 4] = [220.0, 214.0, 205.0, 255.0];

/// Renders the sequence: `(frames, masks)`, the frames as u8 images in `scene.channels`, the
/// masks u8 gray (255 where a square covers the pixel centre, else 0).
///
/// Square `s` starts at a seeded position with a seeded direction and moves `speed_px` per
/// frame, bouncing off the edges; its top-left corner at frame `t` is the bounce of
/// `start + t·velocity` in `[0, width − size] × [0, height − size]`, and it covers the pixels
/// whose centres `(x + ½, y + ½)` lie inside it.
pub fn moving_shapes(scene: &MovingScene) -> Result<(Vec<Image>, Vec<Image>), String> {
    let (w, h) = (scene.width, scene.height);
    if scene.size_px > w || scene.size_px > h {
        return Err(format!(
            "squares of {} px do not fit a {w}×{h} frame",
            scene.size_px
        ));
    }
    let c = scene.channels.count();
    let size = scene.size_px as f64;
    let (range_x, range_y) = ((w - scene.size_px) as f64, (h - scene.size_px) as f64);
    let seed = splitmix64(scene.seed);
    let starts: Vec<[f64; 4]> = (0..scene.shapes as u64)
        .map(|s| {
            let hash = |k: u64| splitmix64(seed ^ (s * 8 + k));
            let angle = std::f64::consts::TAU * unit(hash(2));
            [
                unit(hash(0)) * range_x,
                unit(hash(1)) * range_y,
                scene.speed_px * angle.cos(),
                scene.speed_px * angle.sin(),
            ]
        })
        .collect();
    let mut frames = Vec::with_capacity(scene.frames);
    let mut masks = Vec::with_capacity(scene.frames);
    for t in 0..scene.frames {
        let boxes: Vec<[f64; 2]> = starts
            .iter()
            .map(|&[x0, y0, vx, vy]| {
                [
                    bounce(x0, vx * t as f64, range_x),
                    bounce(y0, vy * t as f64, range_y),
                ]
            })
            .collect();
        let mut frame = Vec::with_capacity(w * h * c);
        let mut mask = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let (cx, cy) = (x as f64 + 0.5, y as f64 + 0.5);
                let covered = boxes
                    .iter()
                    .any(|&[bx, by]| cx >= bx && cx < bx + size && cy >= by && cy < by + size);
                mask.push(if covered { 255u8 } else { 0 });
                let i = ((t * h + y) * w + x) as u64;
                for (ch, &square) in SQUARE_LEVELS.iter().enumerate().take(c) {
                    let clean = if ch == 3 {
                        255.0
                    } else if covered {
                        square
                    } else {
                        background(x as f64, y as f64, ch)
                    };
                    let noise = if ch == 3 || scene.noise_sigma == 0.0 {
                        0.0
                    } else {
                        let k = seed ^ (i * 8 + ch as u64).wrapping_mul(0x2545_F491_4F6C_DD1D);
                        scene.noise_sigma * normal(splitmix64(k), splitmix64(k ^ 0xA5A5))
                    };
                    frame.push((clean + noise).round().clamp(0.0, 255.0) as u8);
                }
            }
        }
        frames.push(Image::from_u8(w, h, scene.channels, frame).map_err(|e| e.to_string())?);
        masks.push(Image::from_u8(w, h, Channels::Gray, mask).map_err(|e| e.to_string())?);
    }
    Ok((frames, masks))
}

/// A generated moving-object sequence with ground truth (`capture.moving_shapes`).
#[derive(Debug, Clone, PartialEq)]
pub struct MovingShapes {
    scene: MovingScene,
}

impl Op for MovingShapes {
    type Params = MovingShapesParams;
    const ID: &'static str = "capture.moving_shapes";
    const SUMMARY: &'static str =
        "Generates a video of squares moving over a textured background, with ground-truth masks.";
    const DOC: &'static str = r#"
Generates `frames` u8 frames of `shapes` bright squares (`size_px` side, levels about 220)
moving at `speed_px` per frame over a static background of smooth stripes and blobs (levels
40–130), bouncing off the edges, plus Gaussian sensor noise of `noise_sigma` levels; and the
ground truth: one u8 mask per frame, 255 where a square covers the pixel centre.

Start positions, directions and noise come from `seed` through SplitMix64 (the noise by
Box–Muller from hashes of the sample index), so the sequence is reproducible and the same at
any thread count. The background never changes, so a background model learns it exactly; the
masks score a segmentation (`analyze.evaluate`, `analyze.roc`).

The moving-object test sequences of background-subtraction evaluations (e.g. the synthetic
videos of the changedetection.net and BMC benchmarks) are the model.

Example:
    "clip": (op: "capture.moving_shapes", params: (frames: 40, shapes: 2, seed: 7)),
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
            ),
            PortSpec::new(
                "masks",
                PortType::Image.list_of(),
                "Ground truth per frame: u8 gray, 255 where a square covers the pixel.",
            ),
        ]
    }

    fn new(params: MovingShapesParams) -> Result<Self, String> {
        let MovingShapesParams {
            width,
            height,
            frames,
            shapes,
            size_px,
            speed_px,
            noise_sigma,
            channels,
            seed,
        } = params;
        if !speed_px.is_finite() || !noise_sigma.is_finite() {
            return Err("`speed_px` and `noise_sigma` must be finite".into());
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
                shapes: shapes as usize,
                size_px: size_px as usize,
                speed_px,
                noise_sigma,
                channels,
                seed,
            },
        })
    }
}

impl Operator for MovingShapes {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let (frames, masks) = moving_shapes(&self.scene).map_err(OpError::failed)?;
        let list = |images: Vec<Image>| {
            Value::list(
                PortType::Image,
                images.into_iter().map(Value::image).collect(),
            )
        };
        Ok(Outputs::new()
            .with("frames", list(frames))
            .with("masks", list(masks)))
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
            shapes: 1,
            size_px: 10,
            speed_px: 3.0,
            noise_sigma: 0.0,
            channels: Channels::Gray,
            seed: 3,
        }
    }

    fn u8s(image: &Image) -> &[u8] {
        image.as_u8().unwrap_or(&[])
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
        let params = MovingShapesParams {
            size_px: 500,
            ..MovingShapesParams::default()
        };
        assert!(MovingShapes::new(params).is_err());
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
