//! `learn.pedestrians`: a procedural pedestrian-detection data set — window-sized crops of
//! upright stick-and-blob figures (positives) and of background clutter (negatives), plus a
//! cluttered scene with figures at known positions and scales.
//!
//! Figures are drawn as unions of capsules (head disc, torso, two legs, two arms) with
//! analytic anti-aliasing: coverage = clamp(r + ½ − d, 0, 1) with d the distance from the
//! pixel centre to the capsule's axis. Everything is drawn sequentially from one seeded
//! SplitMix64 stream: identical for any thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Value};

use super::matrix_value;
use crate::video::filters::SplitMix64;

/// Tiles per row of the training mosaic.
pub const MOSAIC_COLUMNS: usize = 16;

/// Height of the figure (head top to feet) as a fraction of the window height, as the
/// INRIA person windows (96 of 128 px).
pub const FIGURE_FRACTION: f64 = 0.75;

/// Clutter shapes per 1000 px² of background.
const CLUTTER_DENSITY: f64 = 2.0;

params! {
    /// Parameters of `learn.pedestrians`.
    pub struct PedestrianParams {
        /// Detection window `[width, height]`, px (each 8..=512). Default (32, 64).
        window: [u32; 2] = [32, 64],
        /// Positive (figure) training crops, 1..=100000. Default 200.
        positives: u32 = 200 => [min = 1, max = 100000],
        /// Negative (clutter) training crops, 1..=100000. Default 400.
        negatives: u32 = 400 => [min = 1, max = 100000],
        /// Scene `[width, height]`, px (each ≥ the window). Default (256, 160).
        scene: [u32; 2] = [256, 160],
        /// Figures placed in the scene (non-overlapping; fewer if they do not fit). Default 4.
        figures: u32 = 4 => [min = 0, max = 1000],
        /// Largest figure in the scene relative to the window (≥ 1); sizes are uniform in
        /// [1, max_scale] × window. Default 1.6.
        max_scale: f64 = 1.6 => [min = 1.0],
        /// Standard deviation of the Gaussian pixel noise, intensity units (0–1 scale).
        /// Default 0.03.
        noise_sigma: f64 = 0.03 => [min = 0.0],
        /// Random seed. Default 0.
        seed: u64 = 0,
    }
}

/// A capsule: segment (x0, y0)–(x1, y1) with radius r, px.
#[derive(Debug, Clone, Copy)]
struct Capsule {
    a: [f64; 2],
    b: [f64; 2],
    r: f64,
}

impl Capsule {
    fn distance(&self, x: f64, y: f64) -> f64 {
        let (dx, dy) = (self.b[0] - self.a[0], self.b[1] - self.a[1]);
        let len2 = dx * dx + dy * dy;
        let t = if len2 > 0.0 {
            (((x - self.a[0]) * dx + (y - self.a[1]) * dy) / len2).clamp(0.0, 1.0)
        } else {
            0.0
        };
        (x - self.a[0] - t * dx).hypot(y - self.a[1] - t * dy)
    }
}

/// A gray f32 canvas.
struct Canvas {
    w: usize,
    h: usize,
    px: Vec<f32>,
}

impl Canvas {
    /// Blends `value` over the union of `parts` with anti-aliased coverage and opacity `alpha`.
    fn paint(&mut self, parts: &[Capsule], value: f64, alpha: f64) {
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for c in parts {
            x0 = x0.min(c.a[0].min(c.b[0]) - c.r - 1.0);
            y0 = y0.min(c.a[1].min(c.b[1]) - c.r - 1.0);
            x1 = x1.max(c.a[0].max(c.b[0]) + c.r + 1.0);
            y1 = y1.max(c.a[1].max(c.b[1]) + c.r + 1.0);
        }
        let clampx = |v: f64| v.clamp(0.0, self.w as f64) as usize;
        let clampy = |v: f64| v.clamp(0.0, self.h as f64) as usize;
        let (xa, xb, ya, yb) = (clampx(x0), clampx(x1.ceil()), clampy(y0), clampy(y1.ceil()));
        for y in ya..yb {
            for x in xa..xb {
                let (cx, cy) = (x as f64 + 0.5, y as f64 + 0.5);
                let cov = parts
                    .iter()
                    .map(|c| (c.r + 0.5 - c.distance(cx, cy)).clamp(0.0, 1.0))
                    .fold(0.0, f64::max)
                    * alpha;
                if cov > 0.0 {
                    let p = &mut self.px[y * self.w + x];
                    *p = (f64::from(*p) * (1.0 - cov) + value * cov) as f32;
                }
            }
        }
    }
}

/// Smooth background (level, gradient, sinusoidal texture) with random clutter: rectangles,
/// discs and bars of random grey levels.
fn clutter(w: usize, h: usize, rng: &mut SplitMix64) -> Canvas {
    let base = 0.3 + 0.4 * rng.uniform();
    let (gx, gy) = (0.3 * (rng.uniform() - 0.5), 0.3 * (rng.uniform() - 0.5));
    let freq = 0.1 + 0.4 * rng.uniform();
    let angle = std::f64::consts::TAU * rng.uniform();
    let amp = 0.05 * rng.uniform();
    let (ca, sa) = (angle.cos(), angle.sin());
    let mut px = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let (u, v) = (x as f64 / w as f64 - 0.5, y as f64 / h as f64 - 0.5);
            let t = (freq * (x as f64 * ca + y as f64 * sa)).sin();
            px.push((base + gx * u + gy * v + amp * t) as f32);
        }
    }
    let mut canvas = Canvas { w, h, px };
    let size = w.min(h) as f64;
    let count = (CLUTTER_DENSITY * (w * h) as f64 / 1000.0).round() as usize;
    for _ in 0..count {
        let (x, y) = (rng.uniform() * w as f64, rng.uniform() * h as f64);
        let value = rng.uniform();
        let alpha = 0.5 + 0.5 * rng.uniform();
        let kind = rng.uniform();
        let shape = if kind < 0.4 {
            // A short, thick capsule: a box-like blob.
            let half = 2.0 + 0.25 * size * rng.uniform();
            let r = 1.0 + 0.2 * size * rng.uniform();
            Capsule {
                a: [x - half, y],
                b: [x + half, y],
                r,
            }
        } else if kind < 0.7 {
            Capsule {
                a: [x, y],
                b: [x, y],
                r: 2.0 + 0.2 * size * rng.uniform(),
            }
        } else {
            let len = 4.0 + 0.6 * size * rng.uniform();
            let a = std::f64::consts::TAU * rng.uniform();
            Capsule {
                a: [x, y],
                b: [x + len * a.cos(), y + len * a.sin()],
                r: 0.5 + 2.0 * rng.uniform(),
            }
        };
        canvas.paint(&[shape], value, alpha);
    }
    canvas
}

/// Draws a figure framed by the window box (x, y, width, height) as in the training
/// positives: head top at 12.5 % of the height, feet at 87.5 %, random pose and contrast.
fn draw_figure(canvas: &mut Canvas, bx: [f64; 4], rng: &mut SplitMix64) {
    let s = bx[3] * (1.0 + 0.1 * (rng.uniform() - 0.5));
    let cx = bx[0] + 0.5 * bx[2] + 0.04 * s * (rng.uniform() - 0.5);
    let top = bx[1] + 0.5 * bx[3] - 0.5 * FIGURE_FRACTION * s;
    let lean = 0.04 * s * (rng.uniform() - 0.5);
    let stride = 0.12 * s * rng.uniform();
    let swing = 0.08 * s * rng.uniform();
    let width = 1.0 + 0.3 * (rng.uniform() - 0.5);
    let y = |f: f64| top + (f - 0.125) * s;
    let hip = y(0.52);
    let shoulder = y(0.3);
    let parts = [
        Capsule {
            a: [cx + lean, y(0.19)],
            b: [cx + lean, y(0.19)],
            r: 0.06 * s,
        },
        Capsule {
            a: [cx + 0.7 * lean, y(0.29)],
            b: [cx, hip - 0.02 * s],
            r: 0.07 * s * width,
        },
        Capsule {
            a: [cx - 0.03 * s, hip],
            b: [cx - 0.02 * s - stride, y(0.86)],
            r: 0.035 * s,
        },
        Capsule {
            a: [cx + 0.03 * s, hip],
            b: [cx + 0.02 * s + stride, y(0.86)],
            r: 0.035 * s,
        },
        Capsule {
            a: [cx - 0.07 * s * width, shoulder],
            b: [cx - 0.09 * s - swing, y(0.5)],
            r: 0.025 * s,
        },
        Capsule {
            a: [cx + 0.07 * s * width, shoulder],
            b: [cx + 0.09 * s + swing * 0.5, y(0.5)],
            r: 0.025 * s,
        },
    ];
    let value = if rng.uniform() < 0.5 {
        0.02 + 0.2 * rng.uniform()
    } else {
        0.78 + 0.2 * rng.uniform()
    };
    canvas.paint(&parts, value, 1.0);
}

fn add_noise(canvas: &mut Canvas, sigma: f64, rng: &mut SplitMix64) {
    for p in &mut canvas.px {
        let v = f64::from(*p)
            + if sigma > 0.0 {
                rng.normal(0.0, sigma)
            } else {
                0.0
            };
        *p = v.clamp(0.0, 1.0) as f32;
    }
}

/// The generated data set.
#[derive(Debug, Clone, PartialEq)]
pub struct PedestrianSet {
    /// Training crops as a mosaic: [`MOSAIC_COLUMNS`] window-sized tiles per row, row-major,
    /// positives first, gray f32 in [0, 1].
    pub training: Image,
    /// Label of every tile: 1 figure, 0 background.
    pub labels: Vec<f64>,
    /// The scene, gray f32 in [0, 1].
    pub scene: Image,
    /// Window box of every placed figure: (x, y, width, height), px.
    pub truth: Vec<[f64; 4]>,
}

/// Generates the training crops and the scene (see the module docs).
pub fn pedestrian_set(p: &PedestrianParams) -> Result<PedestrianSet, String> {
    let [ww, wh] = p.window.map(|v| v as usize);
    let [sw, sh] = p.scene.map(|v| v as usize);
    let mut rng = SplitMix64::new(p.seed);
    let n = (p.positives + p.negatives) as usize;
    let cols = MOSAIC_COLUMNS.min(n);
    let rows = n.div_ceil(cols);
    let (mw, mh) = (cols * ww, rows * wh);
    let mut mosaic = vec![0.0f32; mw * mh];
    let mut labels = Vec::with_capacity(n);
    for i in 0..n {
        let positive = i < p.positives as usize;
        let mut tile = clutter(ww, wh, &mut rng);
        if positive {
            draw_figure(&mut tile, [0.0, 0.0, ww as f64, wh as f64], &mut rng);
        }
        add_noise(&mut tile, p.noise_sigma, &mut rng);
        let (tx, ty) = ((i % cols) * ww, (i / cols) * wh);
        for y in 0..wh {
            mosaic[(ty + y) * mw + tx..(ty + y) * mw + tx + ww]
                .copy_from_slice(&tile.px[y * ww..(y + 1) * ww]);
        }
        labels.push(f64::from(u8::from(positive)));
    }
    let mut scene = clutter(sw, sh, &mut rng);
    let mut truth: Vec<[f64; 4]> = Vec::new();
    let mut tries = 0;
    while truth.len() < p.figures as usize && tries < 1000 {
        tries += 1;
        let scale = 1.0 + (p.max_scale - 1.0) * rng.uniform();
        let (bw, bh) = (ww as f64 * scale, wh as f64 * scale);
        if bw > sw as f64 || bh > sh as f64 {
            continue;
        }
        let bx = [
            (rng.uniform() * (sw as f64 - bw)).floor(),
            (rng.uniform() * (sh as f64 - bh)).floor(),
            bw,
            bh,
        ];
        // Keep the figures (the middle half of each box) apart.
        let apart = truth.iter().all(|t| {
            (bx[0] + 0.5 * bx[2] - t[0] - 0.5 * t[2]).abs() > 0.5 * (bx[2] + t[2]) * 0.75
                || (bx[1] + 0.5 * bx[3] - t[1] - 0.5 * t[3]).abs() > 0.5 * (bx[3] + t[3])
        });
        if apart {
            draw_figure(&mut scene, bx, &mut rng);
            truth.push(bx);
        }
    }
    add_noise(&mut scene, p.noise_sigma, &mut rng);
    Ok(PedestrianSet {
        training: Image::from_f32(mw, mh, Channels::Gray, mosaic).map_err(|e| e.to_string())?,
        labels,
        scene: Image::from_f32(sw, sh, Channels::Gray, scene.px).map_err(|e| e.to_string())?,
        truth,
    })
}

/// Procedural pedestrian data (`learn.pedestrians`). See [`pedestrian_set`].
#[derive(Debug, Clone, PartialEq)]
pub struct Pedestrians(PedestrianParams);

impl Op for Pedestrians {
    type Params = PedestrianParams;
    const ID: &'static str = "learn.pedestrians";
    const SUMMARY: &'static str =
        "Generates figure / clutter training crops and a scene with figures at known boxes.";
    const DOC: &'static str = r#"
A procedural stand-in for a pedestrian data set such as INRIA Person (Dalal & Triggs 2005),
with exact ground truth. A figure is a union of anti-aliased capsules — head disc, torso, two
legs with a random stride, two arms with a random swing — with random lean, width, size
(±5 %) and horizontal offset, drawn dark or light (random polarity) over the background; it
spans the middle 75 % of its window's height, as INRIA's 96-px people in 128-px windows. The
background is a random level and gradient plus a faint sinusoidal texture and clutter (2 shapes
per 1000 px²: blobs, discs and thin bars of random grey and opacity); Gaussian noise
(`noise_sigma`) is added and values clamped to [0, 1].

Outputs:
- `training`: gray f32 mosaic of `positives` figure crops then `negatives` clutter crops, each
  `window` sized, 16 tiles per row (row-major; a partial last row is black).
- `labels`: n × 1, 1 for a figure tile, 0 for clutter.
- `scene`: gray f32 `scene`-sized clutter with `figures` figures, each framed by a window box
  scaled uniformly in [1, `max_scale`]; boxes are kept apart (fewer figures if 1000 tries do
  not place them all).
- `truth`: m × 4 boxes (x, y, width, height), px — the window that frames each figure as the
  training positives are framed.

Drawn sequentially from one SplitMix64 stream seeded by `seed`.

Example:
    "people": (op: "learn.pedestrians", params: (positives: 150, negatives: 300, figures: 3, seed: 1)),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "training",
                PortType::Image,
                "Gray f32 mosaic of window-sized tiles, 16 per row, positives first.",
            ),
            PortSpec::new("labels", PortType::Matrix, "n × 1: 1 figure, 0 clutter."),
            PortSpec::new("scene", PortType::Image, "Gray f32 scene with figures."),
            PortSpec::new(
                "truth",
                PortType::Matrix,
                "m × 4 figure window boxes: x, y, width, height (px).",
            ),
        ]
    }

    fn new(p: PedestrianParams) -> Result<Self, String> {
        if p.window.iter().any(|&v| !(8..=512).contains(&v)) {
            return Err(format!(
                "`window` sides must be between 8 and 512 px, got {:?}",
                p.window
            ));
        }
        if p.scene[0] < p.window[0] || p.scene[1] < p.window[1] || p.scene.iter().any(|&v| v > 8192)
        {
            return Err(format!(
                "`scene` {:?} must be at least the window {:?} and at most 8192 px",
                p.scene, p.window
            ));
        }
        if p.positives == 0 || p.negatives == 0 {
            return Err("`positives` and `negatives` must be at least 1".into());
        }
        if !(p.max_scale.is_finite() && p.max_scale >= 1.0) {
            return Err(format!("`max_scale` must be ≥ 1, got {}", p.max_scale));
        }
        if !(p.noise_sigma.is_finite() && p.noise_sigma >= 0.0) {
            return Err(format!("`noise_sigma` must be ≥ 0, got {}", p.noise_sigma));
        }
        Ok(Pedestrians(p))
    }
}

impl Operator for Pedestrians {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let set = pedestrian_set(&self.0).map_err(OpError::failed)?;
        let n = set.labels.len();
        let m = set.truth.len();
        Ok(Outputs::new()
            .with("training", Value::image(set.training))
            .with("labels", matrix_value(n, 1, set.labels)?)
            .with("scene", Value::image(set.scene))
            .with("truth", matrix_value(m, 4, set.truth.concat())?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn set_has_the_requested_layout_and_is_reproducible() {
        let p = PedestrianParams {
            positives: 10,
            negatives: 20,
            figures: 3,
            ..PedestrianParams::default()
        };
        let a = pedestrian_set(&p).unwrap();
        assert_eq!(a.training.width(), 16 * 32);
        assert_eq!(a.training.height(), 2 * 64);
        assert_eq!(a.labels.iter().filter(|&&l| l == 1.0).count(), 10);
        assert_eq!(a.truth.len(), 3);
        for t in &a.truth {
            assert!(t[0] >= 0.0 && t[1] >= 0.0 && t[0] + t[2] <= 256.0 && t[1] + t[3] <= 160.0);
            assert!((t[3] / t[2] - 2.0).abs() < 1e-12 && t[3] >= 64.0);
        }
        assert_eq!(a, pedestrian_set(&p).unwrap());
    }

    #[test]
    fn figures_contrast_with_their_surroundings_where_drawn() {
        // Without noise, the figure's torso centre differs from the clutter-only tile drawn
        // from the same stream state.
        let mut rng = SplitMix64::new(4);
        let mut plain = clutter(32, 64, &mut rng);
        let background = plain.px.clone();
        draw_figure(&mut plain, [0.0, 0.0, 32.0, 64.0], &mut rng);
        let changed = plain
            .px
            .iter()
            .zip(&background)
            .filter(|(a, b)| (*a - *b).abs() > 0.05)
            .count();
        // The figure covers roughly 10–25 % of the window.
        assert!((150..600).contains(&changed), "{changed}");
        // Nothing above the head changed (it starts below row 6.6 for any size jitter).
        assert!((0..6 * 32).all(|i| plain.px[i] == background[i]));
    }
}
