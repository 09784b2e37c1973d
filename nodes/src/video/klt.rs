//! `video.track_klt`: pyramidal Lucas–Kanade (KLT) sparse feature tracking with a
//! forward–backward check.
//!
//! [`track_klt`] follows each point from `previous` to `next` through a Gaussian pyramid, coarse
//! to fine (Bouguet 2000). On each level the window of `previous` around the point (bilinear
//! sub-pixel samples) and its Scharr gradients give the 2×2 spatial gradient matrix `G`; the
//! displacement is refined by Newton steps `δ = G⁻¹ Σ (I − J)∇I` until `|δ| < epsilon_px` or
//! `max_iterations`. The result of a level, doubled, seeds the next finer one.
//!
//! How it runs: points are cut into fixed chunks of [`CHUNK`] processed in parallel; each point's
//! arithmetic does not depend on the chunking, so the results are bit-identical for any thread
//! count.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, Keypoint, Matrix, Value};
use rayon::prelude::*;

use super::gray::{Plane, gradients, gray_f32, pyramid};

/// Points per parallel chunk.
pub const CHUNK: usize = 32;

/// Largest window side, px.
pub const MAX_WINDOW: u32 = 255;

/// Largest number of pyramid levels above the base.
pub const MAX_LEVELS: u32 = 16;

params! {
    /// Parameters of `video.track_klt`.
    pub struct TrackKltParams {
        /// Side of the square tracking window, px, odd, 3..=255. Default 21.
        window_px: u32 = 21,
        /// Pyramid levels above the full-resolution one (0 = no pyramid), 0..=16; levels whose
        /// side would drop below the window are skipped. Default 3.
        levels: u32 = 3,
        /// Most Newton iterations per pyramid level, 1..=1000. Default 30.
        max_iterations: u32 = 30,
        /// A level stops refining once a step is shorter than this, px, ≥ 0. Default 0.01.
        epsilon_px: f64 = 0.01,
        /// A point is lost when the smallest eigenvalue of its spatial gradient matrix,
        /// normalised as OpenCV does (gradients in gray levels per px on the 0–255 scale,
        /// divided by the window's pixel count and by 1024), is below this; ≥ 0. Default 1e-4.
        min_eigen_threshold: f64 = 1e-4,
        /// Largest forward–backward error (px) of a kept track: the point is tracked back from
        /// `next` to `previous` and lost when it lands farther than this from where it started.
        /// 0 disables the check (and the backward pass). Default 1.0.
        forward_backward_px: f64 = 1.0,
    }
}

/// Settings of one tracking run (see [`TrackKltParams`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KltSettings {
    /// Window side, px (odd).
    pub window: usize,
    /// Pyramid levels above the base.
    pub levels: usize,
    /// Most iterations per level.
    pub max_iterations: usize,
    /// Convergence step length, px.
    pub epsilon: f32,
    /// Eigenvalue threshold, OpenCV's normalisation.
    pub min_eigen: f32,
    /// Forward–backward threshold, px (0: no backward pass).
    pub forward_backward: f32,
}

impl Default for KltSettings {
    fn default() -> Self {
        KltSettings {
            window: 21,
            levels: 3,
            max_iterations: 30,
            epsilon: 0.01,
            min_eigen: 1e-4,
            forward_backward: 1.0,
        }
    }
}

/// One tracked point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Track {
    /// Position in `next`, px (the input position when lost).
    pub x: f32,
    /// Row in `next`, px.
    pub y: f32,
    /// Whether the point was tracked.
    pub tracked: bool,
    /// Forward–backward error, px; NaN when lost or when the check is off.
    pub error: f32,
}

/// Pyramidal KLT tracking (`video.track_klt`). See [`track_klt`].
#[derive(Debug, Clone, PartialEq)]
pub struct TrackKlt {
    settings: KltSettings,
}

impl Op for TrackKlt {
    type Params = TrackKltParams;
    const ID: &'static str = "video.track_klt";
    const SUMMARY: &'static str =
        "Tracks sparse points from one frame to the next with pyramidal Lucas–Kanade (KLT).";
    const DOC: &'static str = r#"
Follows every input keypoint from `previous` to `next` with the pyramidal Lucas–Kanade feature
tracker (Bouguet 2000). Both frames are converted to gray f32 on the 0–255 scale (u16 / 257,
f32 · 255, RGB by BT.601 luma) and reduced into a Gaussian pyramid (`pyrDown` steps). Coarse to
fine, on each level the `window_px`² window of `previous` around the point is sampled bilinearly
with its Scharr gradients (Scharr / 32, gray levels per px); the 2×2 spatial gradient matrix `G`
and the mismatch vector `b = Σ (I − J)∇I` give Newton steps `δ = G⁻¹ b` on the displacement,
with `next` sampled bilinearly, until `|δ| < epsilon_px` or `max_iterations`. The level's
displacement, doubled, seeds the next finer level. Samples outside a frame read the nearest
edge pixel.

A point is lost (status 0, position left at the input) when, on the finest level, the smallest
eigenvalue of `G` — normalised as OpenCV's `minEigThreshold`: gradients in gray levels per px,
divided by the window area and by 1024 — is below `min_eigen_threshold` (flat patches), when it
ends outside `next`, or when tracking it back from `next` to `previous` lands more than
`forward_backward_px` from its start (occlusions, drift; Kalal et al. 2010). `error` is that
forward–backward distance in px (NaN when lost, or when the check is off with 0).

Differences from OpenCV `calcOpticalFlowPyrLK`: floating point throughout (OpenCV uses 14-bit
fixed-point interpolation weights on u8 frames), edge replication instead of OpenCV's
reflect-101 padded pyramid, no oscillation damping, and the forward–backward check built in
(OpenCV's `err` is a mean intensity residual instead).

Reference: J.-Y. Bouguet, "Pyramidal implementation of the Lucas Kanade feature tracker",
Intel, 2000; OpenCV `cv::calcOpticalFlowPyrLK`.

Example:
    "track": (op: "video.track_klt", inputs: { "previous": "a.image", "next": "b.image", "points": "corners.keypoints" }, params: (window_px: 21, levels: 3)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "previous",
                PortType::Image,
                "First frame, any pixel format.",
            ),
            PortSpec::new(
                "next",
                PortType::Image,
                "Second frame, same size as `previous`, any pixel format.",
            ),
            PortSpec::new(
                "points",
                PortType::Keypoints,
                "Points to track in `previous`.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "points",
                PortType::Keypoints,
                "The points at their tracked positions in `next` (lost ones unmoved), same order.",
            ),
            PortSpec::new("status", PortType::Matrix, "n×1: 1 tracked, 0 lost."),
            PortSpec::new(
                "error",
                PortType::Matrix,
                "n×1 forward–backward error, px (NaN when lost or unchecked).",
            ),
        ]
    }

    fn new(params: TrackKltParams) -> Result<Self, String> {
        let TrackKltParams {
            window_px,
            levels,
            max_iterations,
            epsilon_px,
            min_eigen_threshold,
            forward_backward_px,
        } = params;
        if !(3..=MAX_WINDOW).contains(&window_px) || window_px % 2 == 0 {
            return Err(format!(
                "`window_px` must be odd and between 3 and {MAX_WINDOW}, got {window_px}"
            ));
        }
        if levels > MAX_LEVELS {
            return Err(format!(
                "`levels` must be at most {MAX_LEVELS}, got {levels}"
            ));
        }
        if !(1..=1000).contains(&max_iterations) {
            return Err(format!(
                "`max_iterations` must be between 1 and 1000, got {max_iterations}"
            ));
        }
        for (name, v) in [
            ("epsilon_px", epsilon_px),
            ("min_eigen_threshold", min_eigen_threshold),
            ("forward_backward_px", forward_backward_px),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(format!("`{name}` must be finite and ≥ 0, got {v}"));
            }
        }
        Ok(TrackKlt {
            settings: KltSettings {
                window: window_px as usize,
                levels: levels as usize,
                max_iterations: max_iterations as usize,
                epsilon: epsilon_px as f32,
                min_eigen: min_eigen_threshold as f32,
                forward_backward: forward_backward_px as f32,
            },
        })
    }
}

impl Operator for TrackKlt {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let previous = inputs.image("previous")?;
        let next = inputs.image("next")?;
        let points = match inputs.require("points")? {
            Value::Keypoints(k) => k,
            other => {
                return Err(OpError::input(
                    "points",
                    format!("expected keypoints, got {:?}", other.port_type()),
                ));
            }
        };
        let xy: Vec<[f32; 2]> = points.iter().map(|k| [k.x, k.y]).collect();
        let tracks = track_klt(previous, next, &xy, &self.settings).map_err(OpError::failed)?;
        let moved: Vec<Keypoint> = points
            .iter()
            .zip(&tracks)
            .map(|(k, t)| Keypoint {
                x: t.x,
                y: t.y,
                ..*k
            })
            .collect();
        let n = tracks.len();
        let status = Matrix::new(
            n,
            1,
            tracks
                .iter()
                .map(|t| f64::from(u8::from(t.tracked)))
                .collect(),
        )
        .map_err(|e| OpError::failed(e.to_string()))?;
        let error = Matrix::new(n, 1, tracks.iter().map(|t| f64::from(t.error)).collect())
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("points", Value::Keypoints(Arc::new(moved)))
            .with("status", Value::Matrix(Arc::new(status)))
            .with("error", Value::Matrix(Arc::new(error))))
    }
}

/// One pyramid level of a frame pair: `previous` with its gradients and `next`.
struct Level {
    prev: Plane,
    gx: Plane,
    gy: Plane,
    next: Plane,
    /// Gradients of `next` (for the backward pass).
    ngx: Plane,
    ngy: Plane,
}

/// Tracks `points` (px, in `previous`) into `next`. Both frames must have the same size; any
/// pixel format. See [`TrackKltParams`] for the settings. Returns one [`Track`] per point, in
/// order.
pub fn track_klt(
    previous: &Image,
    next: &Image,
    points: &[[f32; 2]],
    settings: &KltSettings,
) -> Result<Vec<Track>, String> {
    if previous.width() != next.width() || previous.height() != next.height() {
        return Err(format!(
            "`previous` is {}×{} but `next` is {}×{}",
            previous.width(),
            previous.height(),
            next.width(),
            next.height()
        ));
    }
    let lost = |p: &[f32; 2]| Track {
        x: p[0],
        y: p[1],
        tracked: false,
        error: f32::NAN,
    };
    if previous.width() == 0 || previous.height() == 0 || points.is_empty() {
        return Ok(points.iter().map(lost).collect());
    }
    let min_side = (settings.window / 2 + 1).max(1);
    let a = pyramid(&gray_f32(previous), settings.levels, min_side)?;
    let b = pyramid(&gray_f32(next), settings.levels, min_side)?;
    let backward = settings.forward_backward > 0.0;
    let mut levels = Vec::with_capacity(a.len());
    for (prev, next) in a.into_iter().zip(b) {
        let (gx, gy) = gradients(&prev)?;
        let (ngx, ngy) = if backward {
            gradients(&next)?
        } else {
            (next.clone(), next.clone())
        };
        levels.push(Level {
            prev,
            gx,
            gy,
            next,
            ngx,
            ngy,
        });
    }
    let (w, h) = (previous.width() as f32, previous.height() as f32);
    let inside = |x: f32, y: f32| x >= -0.5 && y >= -0.5 && x < w - 0.5 && y < h - 0.5;
    let mut out = vec![lost(&[0.0, 0.0]); points.len()];
    out.par_chunks_mut(CHUNK)
        .zip(points.par_chunks(CHUNK))
        .for_each(|(tracks, pts)| {
            let mut scratch = Scratch::new(settings.window);
            for (t, p) in tracks.iter_mut().zip(pts) {
                *t = lost(p);
                if !p[0].is_finite() || !p[1].is_finite() || !inside(p[0], p[1]) {
                    continue;
                }
                let Some(q) = track_one(&levels, *p, settings, false, &mut scratch) else {
                    continue;
                };
                if !inside(q[0], q[1]) {
                    continue;
                }
                let mut error = f32::NAN;
                if backward {
                    let Some(r) = track_one(&levels, q, settings, true, &mut scratch) else {
                        continue;
                    };
                    error = ((r[0] - p[0]).powi(2) + (r[1] - p[1]).powi(2)).sqrt();
                    if error.is_nan() || error > settings.forward_backward {
                        continue;
                    }
                }
                *t = Track {
                    x: q[0],
                    y: q[1],
                    tracked: true,
                    error,
                };
            }
        });
    Ok(out)
}

/// Per-chunk buffers for one window.
struct Scratch {
    i: Vec<f32>,
    ix: Vec<f32>,
    iy: Vec<f32>,
    j: Vec<f32>,
}

impl Scratch {
    fn new(window: usize) -> Scratch {
        let n = window * window;
        Scratch {
            i: vec![0.0; n],
            ix: vec![0.0; n],
            iy: vec![0.0; n],
            j: vec![0.0; n],
        }
    }
}

/// Fills `dst` (window × window) with bilinear samples of `plane` around `(cx, cy)`: all taps
/// share the same fractional weights; coordinates are clamped to the plane.
#[inline]
fn sample_window(plane: &Plane, cx: f32, cy: f32, window: usize, dst: &mut [f32]) {
    let half = (window / 2) as f32;
    let x0f = (cx - half).floor();
    let y0f = (cy - half).floor();
    let fx = cx - half - x0f;
    let fy = cy - half - y0f;
    let (w00, w01, w10, w11) = (
        (1.0 - fx) * (1.0 - fy),
        fx * (1.0 - fy),
        (1.0 - fx) * fy,
        fx * fy,
    );
    let (pw, ph) = (plane.width as i64, plane.height as i64);
    let x0 = x0f as i64;
    let y0 = y0f as i64;
    let interior = x0 >= 0 && y0 >= 0 && x0 + (window as i64) < pw && y0 + (window as i64) < ph;
    if interior {
        let stride = plane.width;
        for (r, row) in dst.chunks_exact_mut(window).enumerate() {
            let base = (y0 as usize + r) * stride + x0 as usize;
            let top = &plane.data[base..base + window + 1];
            let bottom = &plane.data[base + stride..base + stride + window + 1];
            for (c, d) in row.iter_mut().enumerate() {
                *d = top[c] * w00 + top[c + 1] * w01 + bottom[c] * w10 + bottom[c + 1] * w11;
            }
        }
    } else {
        let cx_ = |x: i64| x.clamp(0, pw - 1) as usize;
        let cy_ = |y: i64| y.clamp(0, ph - 1) as usize;
        for (r, row) in dst.chunks_exact_mut(window).enumerate() {
            let ya = cy_(y0 + r as i64) * plane.width;
            let yb = cy_(y0 + r as i64 + 1) * plane.width;
            for (c, d) in row.iter_mut().enumerate() {
                let xa = cx_(x0 + c as i64);
                let xb = cx_(x0 + c as i64 + 1);
                *d = plane.data[ya + xa] * w00
                    + plane.data[ya + xb] * w01
                    + plane.data[yb + xa] * w10
                    + plane.data[yb + xb] * w11;
            }
        }
    }
}

/// Lanes of the fixed-order partial sums in [`dot3`].
const LANES: usize = 8;

/// Window sums in a fixed order with `LANES` independent partial sums (so they vectorize):
/// without `diff`, `[Σ gx², Σ gx·gy, Σ gy²]`; with `diff = (i, j)`, `[Σ (i − j)·gx,
/// Σ (i − j)·gy, 0]`.
#[inline]
fn dot3(gx: &[f32], gy: &[f32], diff: Option<(&[f32], &[f32])>) -> [f32; 3] {
    let mut s = [[0.0f32; LANES]; 3];
    let n = gx.len().min(gy.len());
    let whole = n - n % LANES;
    match diff {
        None => {
            for (x, y) in gx[..whole]
                .chunks_exact(LANES)
                .zip(gy[..whole].chunks_exact(LANES))
            {
                for l in 0..LANES {
                    s[0][l] += x[l] * x[l];
                    s[1][l] += x[l] * y[l];
                    s[2][l] += y[l] * y[l];
                }
            }
            for k in whole..n {
                s[0][0] += gx[k] * gx[k];
                s[1][0] += gx[k] * gy[k];
                s[2][0] += gy[k] * gy[k];
            }
        }
        Some((i, j)) => {
            let n = n.min(i.len()).min(j.len());
            let whole = n - n % LANES;
            for (((x, y), a), b) in gx[..whole]
                .chunks_exact(LANES)
                .zip(gy[..whole].chunks_exact(LANES))
                .zip(i[..whole].chunks_exact(LANES))
                .zip(j[..whole].chunks_exact(LANES))
            {
                for l in 0..LANES {
                    let d = a[l] - b[l];
                    s[0][l] += d * x[l];
                    s[1][l] += d * y[l];
                }
            }
            for k in whole..n {
                let d = i[k] - j[k];
                s[0][0] += d * gx[k];
                s[1][0] += d * gy[k];
            }
        }
    }
    s.map(|lanes| lanes.iter().sum())
}

/// Tracks one point through the pyramid (`reverse`: from `next` to `previous`). `None` when the
/// finest level's gradient matrix is too weak or the result is not finite.
fn track_one(
    levels: &[Level],
    p: [f32; 2],
    s: &KltSettings,
    reverse: bool,
    scratch: &mut Scratch,
) -> Option<[f32; 2]> {
    let win = s.window;
    let area = (win * win) as f32;
    let mut g = [0.0f32; 2];
    let eps2 = s.epsilon * s.epsilon;
    for (li, level) in levels.iter().enumerate().rev() {
        let (src, gx, gy, dst) = if reverse {
            (&level.next, &level.ngx, &level.ngy, &level.prev)
        } else {
            (&level.prev, &level.gx, &level.gy, &level.next)
        };
        let scale = 1.0 / (1u32 << li) as f32;
        let px = p[0] * scale;
        let py = p[1] * scale;
        sample_window(src, px, py, win, &mut scratch.i);
        sample_window(gx, px, py, win, &mut scratch.ix);
        sample_window(gy, px, py, win, &mut scratch.iy);
        let [a11, a12, a22] = dot3(&scratch.ix, &scratch.iy, None);
        let det = a11 * a22 - a12 * a12;
        let min_eig = (a11 + a22 - ((a11 - a22) * (a11 - a22) + 4.0 * a12 * a12).sqrt())
            / (2.0 * area * 1024.0);
        let weak = min_eig.is_nan() || min_eig < s.min_eigen;
        if weak || det.is_nan() || det <= f32::EPSILON * (a11 + a22).max(1.0) {
            if li == 0 {
                return None;
            }
            g = [g[0] * 2.0, g[1] * 2.0];
            continue;
        }
        let inv = 1.0 / det;
        let mut v = [0.0f32; 2];
        for _ in 0..s.max_iterations {
            sample_window(dst, px + g[0] + v[0], py + g[1] + v[1], win, &mut scratch.j);
            let [b1, b2, _] = dot3(&scratch.ix, &scratch.iy, Some((&scratch.i, &scratch.j)));
            let dx = (a22 * b1 - a12 * b2) * inv;
            let dy = (a11 * b2 - a12 * b1) * inv;
            v[0] += dx;
            v[1] += dy;
            if !v[0].is_finite() || !v[1].is_finite() {
                return None;
            }
            if dx * dx + dy * dy < eps2 {
                break;
            }
        }
        g = [g[0] + v[0], g[1] + v[1]];
        if li > 0 {
            g = [g[0] * 2.0, g[1] * 2.0];
        }
    }
    let q = [p[0] + g[0], p[1] + g[1]];
    (q[0].is_finite() && q[1].is_finite()).then_some(q)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::video::synth::blob_texture;
    use ocellus_engine::value::{Channels, PixelData};

    const IDENTITY: [f64; 6] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0];

    /// Grid of points at least `margin` px inside a `w × h` image.
    fn grid(w: usize, h: usize, margin: usize, step: usize) -> Vec<[f32; 2]> {
        let mut out = Vec::new();
        for y in (margin..h - margin).step_by(step) {
            for x in (margin..w - margin).step_by(step) {
                out.push([x as f32 + 0.25, y as f32 + 0.6]);
            }
        }
        out
    }

    fn median(mut v: Vec<f32>) -> f32 {
        v.sort_by(f32::total_cmp);
        v[v.len() / 2]
    }

    /// Tracks `points` between renderings with `map_a` and `map_b` and returns the end-point
    /// errors of tracked points against `truth(p)`, plus the number lost.
    fn run(
        map_a: [f64; 6],
        map_b: [f64; 6],
        points: &[[f32; 2]],
        truth: impl Fn([f32; 2]) -> [f32; 2],
    ) -> (Vec<f32>, usize) {
        let a = blob_texture(200, 160, 3.0, 7, map_a).unwrap();
        let b = blob_texture(200, 160, 3.0, 7, map_b).unwrap();
        let tracks = track_klt(&a, &b, points, &KltSettings::default()).unwrap();
        let mut errors = Vec::new();
        let mut lost = 0;
        for (p, t) in points.iter().zip(&tracks) {
            if t.tracked {
                let q = truth(*p);
                errors.push(((t.x - q[0]).powi(2) + (t.y - q[1]).powi(2)).sqrt());
            } else {
                lost += 1;
            }
        }
        (errors, lost)
    }

    #[test]
    fn sub_pixel_translation() {
        // next(x) = texture(x − d): content moves by d = (2.3, −1.6).
        let (dx, dy) = (2.3f32, -1.6f32);
        let b = [1.0, 0.0, -f64::from(dx), 0.0, 1.0, -f64::from(dy)];
        let pts = grid(200, 160, 16, 9);
        let (errors, lost) = run(IDENTITY, b, &pts, |p| [p[0] + dx, p[1] + dy]);
        assert!(lost * 20 < pts.len(), "lost {lost} of {}", pts.len());
        let m = median(errors);
        assert!(m < 0.05, "median error {m}");
    }

    #[test]
    fn large_translation_needs_the_pyramid() {
        let (dx, dy) = (13.4f32, 9.2f32);
        let b = [1.0, 0.0, -f64::from(dx), 0.0, 1.0, -f64::from(dy)];
        let pts = grid(200, 160, 30, 11);
        let (errors, lost) = run(IDENTITY, b, &pts, |p| [p[0] + dx, p[1] + dy]);
        assert!(lost * 10 < pts.len(), "lost {lost}");
        assert!(median(errors) < 0.05);
    }

    #[test]
    fn small_rotation() {
        // next shows the texture rotated by 1° about (100, 80): next(x) = tex(R⁻¹(x − c) + c).
        let t = 1f64.to_radians();
        let (c, s) = (t.cos(), t.sin());
        let (cx, cy) = (100.0, 80.0);
        let b = [c, s, cx - c * cx - s * cy, -s, c, cy + s * cx - c * cy];
        let pts = grid(200, 160, 20, 9);
        let (errors, lost) = run(IDENTITY, b, &pts, |p| {
            let (x, y) = (f64::from(p[0]) - cx, f64::from(p[1]) - cy);
            [(c * x - s * y + cx) as f32, (s * x + c * y + cy) as f32]
        });
        assert!(lost * 10 < pts.len(), "lost {lost}");
        let m = median(errors);
        assert!(m < 0.1, "median error {m}");
    }

    #[test]
    fn points_leaving_the_image_are_lost() {
        let b = [1.0, 0.0, 12.0, 0.0, 1.0, 0.0]; // content moves 12 px left
        let pts = [[5.0, 80.0], [8.0, 40.0], [100.0, 80.0]];
        let a = blob_texture(200, 160, 3.0, 7, IDENTITY).unwrap();
        let n = blob_texture(200, 160, 3.0, 7, b).unwrap();
        let t = track_klt(&a, &n, &pts, &KltSettings::default()).unwrap();
        assert!(!t[0].tracked && !t[1].tracked);
        assert!(t[0].error.is_nan());
        assert_eq!([t[0].x, t[0].y], pts[0], "lost points stay put");
        assert!(t[2].tracked && (t[2].x - 88.0).abs() < 0.05);
    }

    #[test]
    fn occluded_patch_fails_forward_backward() {
        let a = blob_texture(200, 160, 3.0, 7, IDENTITY).unwrap();
        let n = blob_texture(200, 160, 3.0, 7, [1.0, 0.0, -1.5, 0.0, 1.0, 0.0]).unwrap();
        // Occluder: a 60×60 square of an unrelated texture at (70..130, 50..110).
        let other = blob_texture(200, 160, 3.0, 99, IDENTITY).unwrap();
        let (PixelData::F32(mut dst), PixelData::F32(src)) = (n.into_data(), other.data()) else {
            panic!()
        };
        for y in 50..110 {
            dst[y * 200 + 70..y * 200 + 130].copy_from_slice(&src[y * 200 + 70..y * 200 + 130]);
        }
        let n = Image::from_f32(200, 160, Channels::Gray, dst).unwrap();
        let inside = grid(200, 160, 0, 1)
            .into_iter()
            .filter(|p| (85.0..115.0).contains(&p[0]) && (65.0..95.0).contains(&p[1]))
            .step_by(37)
            .collect::<Vec<_>>();
        let t = track_klt(&a, &n, &inside, &KltSettings::default()).unwrap();
        let lost = t.iter().filter(|t| !t.tracked).count();
        assert!(
            lost * 10 >= inside.len() * 8,
            "lost {lost} of {}",
            inside.len()
        );
        // Without the check most of them come back "tracked".
        let off = KltSettings {
            forward_backward: 0.0,
            ..KltSettings::default()
        };
        let t = track_klt(&a, &n, &inside, &off).unwrap();
        assert!(t.iter().filter(|t| t.tracked).count() > lost / 2);
        assert!(t.iter().all(|t| t.error.is_nan()));
    }

    #[test]
    fn constant_and_tiny_images() {
        let flat = Image::from_u8(64, 64, Channels::Gray, vec![128; 64 * 64]).unwrap();
        let pts = [[32.0, 32.0], [10.5, 20.25]];
        let t = track_klt(&flat, &flat, &pts, &KltSettings::default()).unwrap();
        assert!(t.iter().all(|t| !t.tracked && t.error.is_nan()));
        for side in [1usize, 2, 8] {
            let img = crate::filter::test_support::random_u8(side, side, Channels::Rgb, 3);
            let pts = [[0.0, 0.0], [side as f32 / 2.0, side as f32 / 2.0]];
            let t = track_klt(&img, &img, &pts, &KltSettings::default()).unwrap();
            assert!(t.iter().all(|t| t.x.is_finite() && t.y.is_finite()));
        }
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        let t = track_klt(&empty, &empty, &pts, &KltSettings::default()).unwrap();
        assert!(t.iter().all(|t| !t.tracked));
        assert!(
            track_klt(&flat, &flat, &[], &KltSettings::default())
                .unwrap()
                .is_empty()
        );
        assert!(track_klt(&flat, &empty, &pts, &KltSettings::default()).is_err());
        // Non-finite inputs are lost, not propagated.
        let t = track_klt(&flat, &flat, &[[f32::NAN, 1.0]], &KltSettings::default()).unwrap();
        assert!(!t[0].tracked);
    }

    #[test]
    fn identical_frames_track_in_place() {
        let a = blob_texture(96, 96, 2.5, 1, IDENTITY).unwrap();
        let pts = grid(96, 96, 12, 7);
        let t = track_klt(&a, &a, &pts, &KltSettings::default()).unwrap();
        for (p, t) in pts.iter().zip(&t) {
            assert!(t.tracked);
            assert!((t.x - p[0]).abs() < 1e-3 && (t.y - p[1]).abs() < 1e-3);
            assert!(t.error < 1e-3);
        }
    }

    #[test]
    fn deterministic_across_thread_counts() {
        let a = blob_texture(160, 120, 3.0, 5, IDENTITY).unwrap();
        let b = blob_texture(160, 120, 3.0, 5, [1.0, 0.02, -1.7, -0.02, 1.0, 0.9]).unwrap();
        let pts = grid(160, 120, 4, 5);
        let runs: Vec<Vec<Track>> = [1, 3, 8]
            .iter()
            .map(|&n| {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(n)
                    .build()
                    .unwrap();
                pool.install(|| track_klt(&a, &b, &pts, &KltSettings::default()).unwrap())
            })
            .collect();
        for r in &runs[1..] {
            for (x, y) in r.iter().zip(&runs[0]) {
                assert_eq!(x.x.to_bits(), y.x.to_bits());
                assert_eq!(x.y.to_bits(), y.y.to_bits());
                assert_eq!(x.tracked, y.tracked);
            }
        }
    }

    #[test]
    fn operator_outputs_and_bad_params() {
        let op = TrackKlt::new(TrackKltParams::default()).unwrap();
        assert_eq!(op.settings, KltSettings::default());
        for bad in [
            TrackKltParams {
                window_px: 20,
                ..Default::default()
            },
            TrackKltParams {
                window_px: 1,
                ..Default::default()
            },
            TrackKltParams {
                levels: 17,
                ..Default::default()
            },
            TrackKltParams {
                max_iterations: 0,
                ..Default::default()
            },
            TrackKltParams {
                epsilon_px: f64::NAN,
                ..Default::default()
            },
            TrackKltParams {
                min_eigen_threshold: -1.0,
                ..Default::default()
            },
            TrackKltParams {
                forward_backward_px: f64::INFINITY,
                ..Default::default()
            },
        ] {
            assert!(TrackKlt::new(bad).is_err());
        }
        let a = blob_texture(64, 64, 2.5, 2, IDENTITY).unwrap();
        let b = blob_texture(64, 64, 2.5, 2, [1.0, 0.0, -1.0, 0.0, 1.0, 0.0]).unwrap();
        let kp = |x, y| Keypoint {
            x,
            y,
            size: 7.0,
            angle: -1.0,
            response: 1.0,
            octave: 0,
        };
        let specs = TrackKlt::inputs();
        let values = vec![
            Some(Value::image(a)),
            Some(Value::image(b)),
            Some(Value::Keypoints(Arc::new(vec![
                kp(32.0, 32.0),
                kp(0.0, 0.0),
            ]))),
        ];
        let mut out = op
            .run(
                &RunContext {
                    node: "t".into(),
                    threads: 1,
                    element: None,
                },
                &Inputs::new(&specs, &values),
            )
            .unwrap();
        let Some(Value::Keypoints(p)) = out.take("points") else {
            panic!()
        };
        assert_eq!(p.len(), 2);
        assert!((p[0].x - 33.0).abs() < 0.05 && p[0].size == 7.0);
        let Some(Value::Matrix(s)) = out.take("status") else {
            panic!()
        };
        assert_eq!((s.rows, s.cols, s.data[0]), (2, 1, 1.0));
        let Some(Value::Matrix(e)) = out.take("error") else {
            panic!()
        };
        assert!(e.data[0] < 0.05);
    }
}
