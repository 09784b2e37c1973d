//! `geometry.stitch_panorama`: views related by homographies warped into one panorama and
//! blended — the compositing half of OpenCV's `Stitcher` (its registration half is the
//! feature, matching and `geometry.find_homography` nodes before it in a graph).
//!
//! The algorithm is [`stitch`]; [`StitchPanorama`] is the thin operator.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Matrix, Metrics, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use crate::filter::warp::invert_3x3;
use crate::geometry::rectify::samples_f32;
use crate::sfm::pairs::required_list;

/// Largest panorama side, px, unless `max_side_px` says otherwise.
pub const DEFAULT_MAX_SIDE_PX: u32 = 16384;

param_enum! {
    /// How overlapping views are combined.
    pub enum Blend {
        /// Weighted mean, each view weighted by the distance to its own border (OpenCV's
        /// `FeatherBlender`): seams fade over the overlap.
        Feather = "feather",
        /// No mixing: each pixel from the view whose border is farthest (a hard seam down the
        /// middle of each overlap).
        None = "none",
    }
}

params! {
    /// Parameters of `geometry.stitch_panorama`.
    pub struct StitchParams {
        /// View whose image plane the panorama is drawn on (0-based); None: the middle one.
        reference: Option<u32> = None,
        /// "feather" (distance-weighted mean) or "none" (hard seams).
        blend: Blend = Blend::Feather,
        /// Largest panorama width or height, px (1..=65536): a bad homography that stretches a
        /// view towards infinity is an error rather than an enormous image.
        max_side_px: u32 = DEFAULT_MAX_SIDE_PX => [min = 1, max = 65536, unit = "px"],
    }
}

/// The panorama compositor (`geometry.stitch_panorama`). See [`stitch`].
#[derive(Debug, Clone, PartialEq)]
pub struct StitchPanorama {
    reference: Option<usize>,
    blend: Blend,
    max_side_px: u32,
}

impl Op for StitchPanorama {
    type Params = StitchParams;
    const ID: &'static str = "geometry.stitch_panorama";
    const SUMMARY: &'static str = "Warps views related by pairwise homographies onto one image plane and blends them into a panorama.";
    const DOC: &'static str = r#"
`images` are views of a plane (or taken from one centre) in order, and `pairwise[k]` is the
homography from view k's pixels to view k+1's (what `geometry.find_homography` estimates from
view k's matches as `points_left` and view k+1's as `points_right`). Every view is mapped onto
the `reference` view's plane by chaining them — Hₖ = H_{r−1} ⋯ Hₖ before the reference,
H_{r}⁻¹ ⋯ H_{k−1}⁻¹ after it — and the panorama is the box around all mapped views, shifted to
start at (0, 0). Each output pixel samples every view that covers it (bilinear, pixel centres
at integer coordinates as in the feature detectors) and combines them by `blend`:

- "feather": the mean weighted by each sample's distance to its own view's border (R. Szeliski,
  "Image Alignment and Stitching: A Tutorial", 2006, §6.2; OpenCV's `FeatherBlender`);
- "none": the sample farthest from its view's border alone (a hard seam through each overlap).

A view that the chain folds through infinity (a corner mapped behind the reference plane) or
a panorama larger than `max_side_px` is an error naming the view; choose another reference or
check the homographies. Views must share one channel layout; the panorama has it and the
first view's sample type (u8 and u16 rounded and clamped). No exposure compensation: the
views are assumed equally exposed.

Outputs: `panorama`; `coverage` (u8 gray: how many views cover each pixel); `homographies`
(List<Matrix>: view k's pixels → panorama pixels); `metrics`: width, height, views, reference,
covered_fraction (share of the box covered), overlap_fraction (share covered twice or more),
overlap_rms (RMS difference between two views' samples where they overlap, image units —
how well the views are registered; 0 for a perfect registration of identical exposures).

Example:
    "pano": (op: "geometry.stitch_panorama",
             inputs: { "images": ["v0.image", "v1.image", "v2.image"],
                       "pairwise": ["h01.H", "h12.H"] },
             params: (blend: "feather")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "images",
                PortType::Image.list_of(),
                "The views in order, one channel layout.",
            ),
            PortSpec::new(
                "pairwise",
                PortType::Matrix.list_of(),
                "n − 1 homographies, entry k from view k's pixels to view k+1's.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("panorama", PortType::Image, "The blended panorama."),
            PortSpec::new(
                "coverage",
                PortType::Image,
                "u8 gray: number of views covering each pixel.",
            ),
            PortSpec::new(
                "homographies",
                PortType::Matrix.list_of(),
                "Per view: its pixels → panorama pixels.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "width, height, views, reference, covered_fraction, overlap_fraction, overlap_rms.",
            ),
        ]
    }

    fn new(params: StitchParams) -> Result<Self, String> {
        Ok(StitchPanorama {
            reference: params.reference.map(|r| r as usize),
            blend: params.blend,
            max_side_px: params.max_side_px,
        })
    }
}

impl Operator for StitchPanorama {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let images = required_list(inputs, "images", PortType::Image, |v| match v {
            Value::Image(i) => Some(Arc::clone(i)),
            _ => None,
        })?;
        let pairwise = required_list(inputs, "pairwise", PortType::Matrix, |v| match v {
            Value::Matrix(m) => Some(Arc::clone(m)),
            _ => None,
        })?;
        let Some(first) = images.first() else {
            return Err(OpError::input("images", "no views"));
        };
        let channels = first.channels();
        let mut views = Vec::with_capacity(images.len());
        for (k, image) in images.iter().enumerate() {
            if image.channels() != channels {
                return Err(OpError::input(
                    "images",
                    format!(
                        "view {k} is {} but view 0 is {}: convert them to one layout",
                        image.channels().name(),
                        channels.name()
                    ),
                ));
            }
            if image.width() == 0 || image.height() == 0 {
                return Err(OpError::input("images", format!("view {k} is empty")));
            }
            let samples = samples_f32(image);
            if samples.iter().any(|v| !v.is_finite()) {
                return Err(OpError::input(
                    "images",
                    format!("view {k} holds a non-finite sample"),
                ));
            }
            views.push(View {
                width: image.width(),
                height: image.height(),
                samples,
            });
        }
        let mut chain = Vec::with_capacity(pairwise.len());
        for (k, m) in pairwise.iter().enumerate() {
            if m.rows != 3 || m.cols != 3 || m.data.len() != 9 {
                return Err(OpError::input(
                    "pairwise",
                    format!("homography {k} must be 3×3, got {}×{}", m.rows, m.cols),
                ));
            }
            let mut h = [0.0; 9];
            h.copy_from_slice(&m.data);
            chain.push(h);
        }
        let config = StitchConfig {
            reference: self.reference,
            blend: self.blend,
            max_side_px: self.max_side_px as usize,
            channels: channels.count(),
        };
        let pano = stitch(&views, &chain, &config).map_err(|e| match e {
            StitchError::Homography { .. } | StitchError::Count { .. } => {
                OpError::input("pairwise", e.to_string())
            }
            _ => OpError::input("images", e.to_string()),
        })?;
        let (w, h) = (pano.width, pano.height);
        let panorama = match first.data() {
            PixelData::U8(_) => Image::from_u8(
                w,
                h,
                channels,
                pano.samples
                    .iter()
                    .map(|v| v.round().clamp(0.0, 255.0) as u8)
                    .collect(),
            ),
            PixelData::U16(_) => Image::from_u16(
                w,
                h,
                channels,
                pano.samples
                    .iter()
                    .map(|v| v.round().clamp(0.0, 65535.0) as u16)
                    .collect(),
            ),
            PixelData::F32(_) => Image::from_f32(w, h, channels, pano.samples),
        }
        .map_err(|e| OpError::failed(e.to_string()))?;
        let coverage = Image::from_u8(w, h, Channels::Gray, pano.coverage)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let homographies = pano
            .panorama_from_view
            .iter()
            .map(|h| {
                Matrix::new(3, 3, h.to_vec())
                    .map(|m| Value::Matrix(Arc::new(m)))
                    .map_err(|e| OpError::failed(e.to_string()))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let mut metrics = Metrics::new();
        metrics.insert("width".into(), w as f64);
        metrics.insert("height".into(), h as f64);
        metrics.insert("views".into(), views.len() as f64);
        metrics.insert("reference".into(), pano.reference as f64);
        metrics.insert("covered_fraction".into(), pano.covered_fraction);
        metrics.insert("overlap_fraction".into(), pano.overlap_fraction);
        metrics.insert("overlap_rms".into(), pano.overlap_rms);
        Ok(Outputs::new()
            .with("panorama", Value::image(panorama))
            .with("coverage", Value::image(coverage))
            .with("homographies", Value::list(PortType::Matrix, homographies))
            .with("metrics", Value::metrics(metrics)))
    }
}

/// One view: interleaved samples, `channels` per pixel.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    /// Width, px.
    pub width: usize,
    /// Height, px.
    pub height: usize,
    /// Row-major interleaved samples.
    pub samples: Vec<f32>,
}

/// Settings of [`stitch`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StitchConfig {
    /// Reference view (None: the middle one).
    pub reference: Option<usize>,
    /// Blending.
    pub blend: Blend,
    /// Largest side, px.
    pub max_side_px: usize,
    /// Samples per pixel of every view.
    pub channels: usize,
}

/// The result of [`stitch`].
#[derive(Debug, Clone, PartialEq)]
pub struct Panorama {
    /// Width, px.
    pub width: usize,
    /// Height, px.
    pub height: usize,
    /// Interleaved samples (0 where no view covers).
    pub samples: Vec<f32>,
    /// Views covering each pixel (saturating at 255).
    pub coverage: Vec<u8>,
    /// Per view: its pixels → panorama pixels, row-major 3×3.
    pub panorama_from_view: Vec<[f64; 9]>,
    /// The reference view.
    pub reference: usize,
    /// Share of pixels covered by a view.
    pub covered_fraction: f64,
    /// Share of pixels covered by two views or more.
    pub overlap_fraction: f64,
    /// RMS difference of overlapping views' samples, image units.
    pub overlap_rms: f64,
}

/// Why views cannot be stitched.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StitchError {
    /// The homography list does not pair up with the views.
    #[error("{views} views need {} pairwise homographies, got {homographies}", views.saturating_sub(1))]
    Count {
        /// Views given.
        views: usize,
        /// Homographies given.
        homographies: usize,
    },
    /// A pairwise homography is unusable.
    #[error("homography {index}: {reason}")]
    Homography {
        /// Its index.
        index: usize,
        /// What is wrong.
        reason: String,
    },
    /// The reference is not a view.
    #[error("reference {reference} is not a view (there are {views})")]
    Reference {
        /// Asked for.
        reference: usize,
        /// Views given.
        views: usize,
    },
    /// A view's samples do not fill it.
    #[error("view {index} holds {actual} samples, {expected} expected")]
    Samples {
        /// The view.
        index: usize,
        /// Expected count.
        expected: usize,
        /// Actual count.
        actual: usize,
    },
    /// The chain sends a view's corner through infinity.
    #[error(
        "view {index} folds through infinity on the reference view's plane (a corner maps behind it); choose another reference or check the homographies"
    )]
    Fold {
        /// The view.
        index: usize,
    },
    /// The panorama would be too large.
    #[error(
        "the panorama would be {width}×{height} px, more than max_side_px = {max} on a side; a homography stretches a view too far"
    )]
    TooLarge {
        /// Width it would have.
        width: f64,
        /// Height it would have.
        height: f64,
        /// The limit.
        max: usize,
    },
}

fn mul(a: &[f64; 9], b: &[f64; 9]) -> [f64; 9] {
    let mut c = [0.0; 9];
    for i in 0..3 {
        for j in 0..3 {
            c[3 * i + j] = (0..3).map(|k| a[3 * i + k] * b[3 * k + j]).sum();
        }
    }
    c
}

/// The inverse of a 3×3 matrix, None when it is singular.
fn invert(m: &[f64; 9]) -> Option<[f64; 9]> {
    invert_3x3(m).ok()
}

/// (x, y, w) of `h` · (x, y, 1).
fn apply(h: &[f64; 9], x: f64, y: f64) -> (f64, f64, f64) {
    let w = h[6] * x + h[7] * y + h[8];
    (
        (h[0] * x + h[1] * y + h[2]) / w,
        (h[3] * x + h[4] * y + h[5]) / w,
        w,
    )
}

/// Each view's homography onto the reference view's plane (see `geometry.stitch_panorama`).
pub fn chain_to_reference(
    pairwise: &[[f64; 9]],
    views: usize,
    reference: usize,
) -> Result<Vec<[f64; 9]>, StitchError> {
    if pairwise.len() + 1 != views {
        return Err(StitchError::Count {
            views,
            homographies: pairwise.len(),
        });
    }
    if reference >= views {
        return Err(StitchError::Reference { reference, views });
    }
    for (index, h) in pairwise.iter().enumerate() {
        if h.iter().any(|v| !v.is_finite()) {
            return Err(StitchError::Homography {
                index,
                reason: "holds a non-finite entry".into(),
            });
        }
    }
    let inverses: Vec<[f64; 9]> = pairwise
        .iter()
        .enumerate()
        .map(|(index, h)| {
            invert(h).ok_or_else(|| StitchError::Homography {
                index,
                reason: "is singular".into(),
            })
        })
        .collect::<Result<_, _>>()?;
    let identity = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
    let mut to_reference = vec![identity; views];
    for k in (0..reference).rev() {
        to_reference[k] = mul(&to_reference[k + 1], &pairwise[k]);
    }
    for k in reference + 1..views {
        to_reference[k] = mul(&to_reference[k - 1], &inverses[k - 1]);
    }
    Ok(to_reference)
}

/// Distance of (x, y) to the border of a `w × h` view (pixel centres at integers), ≥ 0 inside.
fn border_distance(x: f64, y: f64, w: usize, h: usize) -> f64 {
    let dx = (x + 0.5).min(w as f64 - 0.5 - x);
    let dy = (y + 0.5).min(h as f64 - 0.5 - y);
    dx.min(dy)
}

/// Bilinear sample of `view` at (x, y) (inside `[0, w−1] × [0, h−1]`) into `out`.
fn sample(view: &View, channels: usize, x: f64, y: f64, out: &mut [f32]) {
    let x0 = (x.floor() as usize).min(view.width - 1);
    let y0 = (y.floor() as usize).min(view.height - 1);
    let x1 = (x0 + 1).min(view.width - 1);
    let y1 = (y0 + 1).min(view.height - 1);
    let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    let at = |xx: usize, yy: usize, c: usize| view.samples[(yy * view.width + xx) * channels + c];
    for (c, o) in out.iter_mut().enumerate() {
        let top = at(x0, y0, c) * (1.0 - fx) + at(x1, y0, c) * fx;
        let bottom = at(x0, y1, c) * (1.0 - fx) + at(x1, y1, c) * fx;
        *o = top * (1.0 - fy) + bottom * fy;
    }
}

/// Stitches `views` related by `pairwise` homographies (entry k: view k → view k+1) into a
/// panorama on the reference view's plane (see `geometry.stitch_panorama`).
pub fn stitch(
    views: &[View],
    pairwise: &[[f64; 9]],
    config: &StitchConfig,
) -> Result<Panorama, StitchError> {
    let channels = config.channels.max(1);
    for (index, v) in views.iter().enumerate() {
        let expected = v.width * v.height * channels;
        if v.samples.len() != expected || v.width == 0 || v.height == 0 {
            return Err(StitchError::Samples {
                index,
                expected,
                actual: v.samples.len(),
            });
        }
    }
    let reference = config.reference.unwrap_or(views.len() / 2);
    let to_reference = chain_to_reference(pairwise, views.len(), reference)?;
    // The box around every mapped view's corners (the view's image is convex as long as no
    // point crosses infinity, which the corners' signs rule out).
    let (mut min_x, mut min_y, mut max_x, mut max_y) = (
        f64::INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NEG_INFINITY,
    );
    for (index, (v, h)) in views.iter().zip(&to_reference).enumerate() {
        let (w, hh) = ((v.width - 1) as f64, (v.height - 1) as f64);
        for (x, y) in [(0.0, 0.0), (w, 0.0), (w, hh), (0.0, hh)] {
            let (px, py, pw) = apply(h, x, y);
            if pw.is_nan() || pw <= 0.0 || !px.is_finite() || !py.is_finite() {
                return Err(StitchError::Fold { index });
            }
            min_x = min_x.min(px);
            min_y = min_y.min(py);
            max_x = max_x.max(px);
            max_y = max_y.max(py);
        }
    }
    let width = (max_x.floor() - min_x.ceil() + 1.0).max(1.0);
    let height = (max_y.floor() - min_y.ceil() + 1.0).max(1.0);
    if width > config.max_side_px as f64 || height > config.max_side_px as f64 {
        return Err(StitchError::TooLarge {
            width: width.ceil(),
            height: height.ceil(),
            max: config.max_side_px,
        });
    }
    let (width, height) = (width as usize, height as usize);
    let shift = [
        1.0,
        0.0,
        -min_x.ceil(),
        0.0,
        1.0,
        -min_y.ceil(),
        0.0,
        0.0,
        1.0,
    ];
    let panorama_from_view: Vec<[f64; 9]> = to_reference.iter().map(|h| mul(&shift, h)).collect();
    let view_from_panorama: Vec<[f64; 9]> = panorama_from_view
        .iter()
        .enumerate()
        .map(|(index, h)| invert(h).ok_or(StitchError::Fold { index }))
        .collect::<Result<_, _>>()?;

    struct RowResult {
        samples: Vec<f32>,
        coverage: Vec<u8>,
        covered: usize,
        overlapped: usize,
        diff_sq: f64,
        diff_count: usize,
    }
    let rows: Vec<RowResult> = (0..height)
        .into_par_iter()
        .map(|y| {
            let mut row = RowResult {
                samples: vec![0.0; width * channels],
                coverage: vec![0; width],
                covered: 0,
                overlapped: 0,
                diff_sq: 0.0,
                diff_count: 0,
            };
            let mut value = vec![0.0f32; channels];
            let mut first = vec![0.0f32; channels];
            let mut sum = vec![0.0f64; channels];
            for x in 0..width {
                let mut weight_sum = 0.0f64;
                let mut best_weight = 0.0f64;
                let mut count = 0usize;
                sum.iter_mut().for_each(|s| *s = 0.0);
                for (view, h) in views.iter().zip(&view_from_panorama) {
                    let (vx, vy, w) = apply(h, x as f64, y as f64);
                    if w.is_nan()
                        || w <= 0.0
                        || !(0.0..=(view.width - 1) as f64).contains(&vx)
                        || !(0.0..=(view.height - 1) as f64).contains(&vy)
                    {
                        continue;
                    }
                    sample(view, channels, vx, vy, &mut value);
                    let weight = border_distance(vx, vy, view.width, view.height).max(1e-3);
                    if count == 0 {
                        first.copy_from_slice(&value);
                    } else if count == 1 {
                        for (a, b) in first.iter().zip(&value) {
                            let d = f64::from(a - b);
                            row.diff_sq += d * d;
                            row.diff_count += 1;
                        }
                    }
                    count += 1;
                    match config.blend {
                        Blend::Feather => {
                            for (s, v) in sum.iter_mut().zip(&value) {
                                *s += weight * f64::from(*v);
                            }
                            weight_sum += weight;
                        }
                        Blend::None => {
                            if weight > best_weight {
                                best_weight = weight;
                                for (s, v) in sum.iter_mut().zip(&value) {
                                    *s = f64::from(*v);
                                }
                                weight_sum = 1.0;
                            }
                        }
                    }
                }
                if count == 0 {
                    continue;
                }
                row.covered += 1;
                if count > 1 {
                    row.overlapped += 1;
                }
                row.coverage[x] = count.min(255) as u8;
                for (c, s) in sum.iter().enumerate() {
                    row.samples[x * channels + c] = (s / weight_sum) as f32;
                }
            }
            row
        })
        .collect();
    let mut samples = Vec::with_capacity(width * height * channels);
    let mut coverage = Vec::with_capacity(width * height);
    let (mut covered, mut overlapped, mut diff_sq, mut diff_count) = (0usize, 0usize, 0.0, 0usize);
    for r in rows {
        samples.extend_from_slice(&r.samples);
        coverage.extend_from_slice(&r.coverage);
        covered += r.covered;
        overlapped += r.overlapped;
        diff_sq += r.diff_sq;
        diff_count += r.diff_count;
    }
    let pixels = (width * height) as f64;
    Ok(Panorama {
        width,
        height,
        samples,
        coverage,
        panorama_from_view,
        reference,
        covered_fraction: covered as f64 / pixels,
        overlap_fraction: overlapped as f64 / pixels,
        overlap_rms: if diff_count > 0 {
            (diff_sq / diff_count as f64).sqrt()
        } else {
            0.0
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth but structured test signal over the plane.
    fn scene(x: f64, y: f64) -> f32 {
        (100.0 + 60.0 * (x * 0.05).sin() * (y * 0.07).cos() + 0.2 * x - 0.1 * y) as f32
    }

    /// A `w × h` gray view whose pixel p shows the scene at `scene_from_view` · p.
    fn render(scene_from_view: &[f64; 9], w: usize, h: usize) -> View {
        let mut samples = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let (sx, sy, _) = apply(scene_from_view, x as f64, y as f64);
                samples.push(scene(sx, sy));
            }
        }
        View {
            width: w,
            height: h,
            samples,
        }
    }

    fn config(blend: Blend) -> StitchConfig {
        StitchConfig {
            reference: None,
            blend,
            max_side_px: 4096,
            channels: 1,
        }
    }

    /// Three views of a plane, the outer two rotated and put in perspective; the pairwise
    /// homographies are exact, so the panorama must be the scene itself on the middle view's
    /// plane, up to bilinear interpolation, and the overlaps must agree.
    #[test]
    fn exact_homographies_rebuild_the_scene() {
        let (w, h) = (80, 60);
        let scene_from: [[f64; 9]; 3] = [
            [0.98, -0.05, 0.0, 0.05, 0.98, 4.0, 0.0002, 0.0, 1.0],
            [1.0, 0.0, 55.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            [1.01, 0.04, 112.0, -0.04, 1.01, -3.0, 0.0, 0.0001, 1.0],
        ];
        let views: Vec<View> = scene_from.iter().map(|m| render(m, w, h)).collect();
        // view k → scene → view k+1.
        let pairwise: Vec<[f64; 9]> = (0..2)
            .map(|k| mul(&invert(&scene_from[k + 1]).unwrap(), &scene_from[k]))
            .collect();
        for blend in [Blend::Feather, Blend::None] {
            let pano = stitch(&views, &pairwise, &config(blend)).unwrap();
            assert_eq!(pano.reference, 1);
            // About 80 + 2·57 px wide.
            assert!((180..=205).contains(&pano.width), "{}", pano.width);
            assert!(pano.overlap_fraction > 0.1, "{}", pano.overlap_fraction);
            assert!(
                pano.overlap_rms < 0.6,
                "{blend:?}: overlap rms {}",
                pano.overlap_rms
            );
            // Every covered pixel shows the scene point the middle view's mapping gives it.
            let view_from_pano = invert(&pano.panorama_from_view[1]).unwrap();
            let mut worst = 0.0f32;
            for y in 0..pano.height {
                for x in 0..pano.width {
                    let i = y * pano.width + x;
                    if pano.coverage[i] == 0 {
                        continue;
                    }
                    let (vx, vy, _) = apply(&view_from_pano, x as f64, y as f64);
                    let (sx, sy, _) = apply(&scene_from[1], vx, vy);
                    worst = worst.max((pano.samples[i] - scene(sx, sy)).abs());
                }
            }
            assert!(worst < 1.5, "{blend:?}: worst error {worst}");
        }
    }

    /// The middle view lands unchanged (shifted only) on its own plane.
    #[test]
    fn the_reference_is_only_shifted() {
        let views = vec![
            render(&[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], 20, 10),
            render(&[1.0, 0.0, 10.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], 20, 10),
        ];
        let shift = [1.0, 0.0, -10.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        let mut c = config(Blend::None);
        c.reference = Some(0);
        let pano = stitch(&views, &[shift], &c).unwrap();
        assert_eq!((pano.width, pano.height), (30, 10));
        assert_eq!(
            pano.panorama_from_view[0],
            [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        );
        assert_eq!(&pano.samples[..20], &views[0].samples[..20]);
        assert_eq!(pano.overlap_fraction, 10.0 * 10.0 / 300.0);
        assert_eq!(pano.coverage[0], 1);
        assert_eq!(pano.coverage[15], 2);
    }

    #[test]
    fn bad_inputs_are_errors() {
        let v = render(&[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], 8, 8);
        let views = vec![v.clone(), v];
        let id = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        let c = config(Blend::Feather);
        assert!(matches!(
            stitch(&views, &[], &c),
            Err(StitchError::Count { .. })
        ));
        assert!(matches!(
            stitch(&views, &[[0.0; 9]], &c),
            Err(StitchError::Homography { index: 0, .. })
        ));
        let mut far = c;
        far.reference = Some(5);
        assert!(matches!(
            stitch(&views, &[id], &far),
            Err(StitchError::Reference { .. })
        ));
        // A perspective that sends part of view 0 behind the reference plane.
        let fold = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, -0.5, 0.0, 1.0];
        let mut first = c;
        first.reference = Some(1);
        assert!(matches!(
            stitch(&views, &[fold], &first),
            Err(StitchError::Fold { index: 0 })
        ));
        // A huge stretch.
        let stretch = [1000.0, 0.0, 0.0, 0.0, 1000.0, 0.0, 0.0, 0.0, 1.0];
        assert!(matches!(
            stitch(&views, &[stretch], &first),
            Err(StitchError::TooLarge { .. })
        ));
    }
}
