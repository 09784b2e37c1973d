//! `video.flow_lk`: dense pyramidal Lucas–Kanade optical flow.
//!
//! [`flow_lk`] solves, at every pixel, the Lucas–Kanade least-squares problem over a
//! Gaussian-weighted window: the 2×2 structure tensor `G = w ∗ (∇I ∇Iᵀ)` of `previous` and the
//! mismatch `b = w ∗ (∇I · I_t)` against `next` warped by the current flow give Gauss–Newton
//! steps `δ = −G⁻¹ b`, coarse to fine over a pyramid.
//!
//! How it runs: per-pixel passes and Gaussian window sums on fixed row bands in parallel; every
//! output sample depends only on its inputs, so results are bit-identical for any thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::value::{Channels, Image};
use rayon::prelude::*;

use super::flow::{
    BAND_ROWS, FlowField, check_pair, check_pyramid_params, flow_pyramid, upsample, warp,
};
use super::gray::{Plane, gradients, plane_of};
use super::horn_schunck::{flow_inputs, flow_outputs, run_flow};
use crate::filter::border::BorderMode;
use crate::filter::gaussian::gaussian_blur;

/// Largest window side, px.
pub const MAX_WINDOW: u32 = 101;

/// Largest number of iterations per level.
pub const MAX_ITERATIONS: u32 = 1000;

params! {
    /// Parameters of `video.flow_lk`.
    pub struct FlowLkParams {
        /// Side of the Gaussian window, px, odd, 3..=101; σ = 0.3·((window − 1)/2 − 1) + 0.8
        /// (OpenCV's rule for a kernel size). Default 15.
        window_px: u32 = 15,
        /// Pyramid levels above the full-resolution one, 0..=16; levels with a side under 8 px
        /// are not built. Default 4.
        levels: u32 = 4,
        /// Size ratio between successive pyramid levels, 0.25..=0.95; 0.5 uses `pyrDown`
        /// steps. Default 0.5.
        scale: f64 = 0.5,
        /// Gauss–Newton iterations (warp + solve) per level, 1..=1000. Default 5.
        iterations: u32 = 5,
        /// A pixel's structure tensor is ill-conditioned when its smallest eigenvalue,
        /// normalised as in `video.track_klt` (Gaussian-weighted mean of the gradient products,
        /// gradients in gray levels per px on the 0–255 scale, divided by 1024), is below this;
        /// ≥ 0. Default 1e-4.
        min_eigenvalue: f64 = 1e-4,
    }
}

/// Settings of one dense Lucas–Kanade run (see [`FlowLkParams`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LkSettings {
    /// Window side, px (odd).
    pub window: usize,
    /// Pyramid levels above the base.
    pub levels: usize,
    /// Pyramid scale factor.
    pub scale: f64,
    /// Iterations per level.
    pub iterations: usize,
    /// Eigenvalue threshold.
    pub min_eigenvalue: f32,
}

impl Default for LkSettings {
    fn default() -> Self {
        LkSettings {
            window: 15,
            levels: 4,
            scale: 0.5,
            iterations: 5,
            min_eigenvalue: 1e-4,
        }
    }
}

/// Dense Lucas–Kanade flow (`video.flow_lk`). See [`flow_lk`].
#[derive(Debug, Clone, PartialEq)]
pub struct FlowLk {
    settings: LkSettings,
}

impl Op for FlowLk {
    type Params = FlowLkParams;
    const ID: &'static str = "video.flow_lk";
    const SUMMARY: &'static str =
        "Dense optical flow by per-pixel pyramidal Lucas–Kanade with a Gaussian window.";
    const DOC: &'static str = r#"
Estimates the motion of every pixel from `previous` to `next` with the Lucas–Kanade method
applied densely: each pixel's flow is the least-squares translation of the Gaussian-weighted
window around it, refined coarse to fine with warping (the dense counterpart of
`video.track_klt`).

Frames are converted to gray f32 on the 0–255 scale (u16 / 257, f32 · 255, RGB by BT.601
luma) and reduced into a pyramid (`levels` levels, each `scale` times smaller; 0.5 uses `pyrDown`,
other factors a Gaussian blur of σ = 1/√(2·scale) and bilinear resampling). On each level the
Scharr gradients of `previous` give the structure tensor `G = w ∗ (∇I ∇Iᵀ)`, `w` the normalised
Gaussian window of side `window_px` (σ from the side as OpenCV's `getGaussianKernel`), once per
level. Each of the `iterations` then warps `next` by the current flow (bicubic, Catmull–Rom),
`I_t = next(x + u) − previous(x)` (zero where the warped point leaves the frame), forms
`b = w ∗ (∇I · I_t)` and updates the flow by `−G⁻¹ b` (a Gauss–Newton step of the window's
sum of squared differences). The flow of a level, resampled and scaled, starts the next finer
one; the coarsest starts from zero.

Ill-conditioned pixels: where the smallest eigenvalue of `G` (a weighted mean of gradient
products in gray levels² per px², divided by 1024 as `video.track_klt` and OpenCV's
`minEigThreshold` do) is below `min_eigenvalue`, or `G` is singular, the level makes no update:
the pixel keeps the flow it got from the coarser level (the bilinear resampling of the coarser
flow, i.e. the motion of its wider neighbourhood), and zero on the coarsest level. A flat frame
therefore gets zero flow everywhere.

Outputs: `u` and `v`, gray f32 images with the flow in px (the content at (x, y) in `previous` is
at (x + u, y + v) in `next`), the convention of `video.block_match` and of `filter.lic`'s `vx` /
`vy`; `visualization`, RGB u8, the Middlebury colour coding (hue = direction, saturation =
length relative to the largest in the field, white = still).

Speed and accuracy: each iteration costs one warp and two Gaussian window sums (O(window) per
pixel), so time grows with `iterations × window_px`. More `levels` recover larger motions (about
2^levels px at scale 0.5) at little cost; more `iterations` converge further for sub-pixel
accuracy (3–5 usually suffice). A larger `window_px` is more robust to noise and to flat
regions but blurs motion boundaries and biases non-translational motion; a smaller one is
sharper and noisier. `min_eigenvalue` only decides where the coarser flow is kept.

Differences from OpenCV: OpenCV's `calcOpticalFlowPyrLK` is sparse (use `video.track_klt`);
its dense flows are Farnebäck's polynomial expansion and DIS. Floating point throughout.

References: B. D. Lucas, T. Kanade, "An iterative image registration technique with an
application to stereo vision", IJCAI 1981; J.-Y. Bouguet, "Pyramidal implementation of the Lucas
Kanade feature tracker", Intel 2000; S. Baker, I. Matthews, "Lucas-Kanade 20 years on", IJCV 2004.

Example:
    "flow": (op: "video.flow_lk", inputs: { "previous": "a.image", "next": "b.image" }, params: (window_px: 15, levels: 4, iterations: 5)),
"#;

    fn inputs() -> Vec<PortSpec> {
        flow_inputs()
    }

    fn outputs() -> Vec<PortSpec> {
        flow_outputs()
    }

    fn new(params: FlowLkParams) -> Result<Self, String> {
        let FlowLkParams {
            window_px,
            levels,
            scale,
            iterations,
            min_eigenvalue,
        } = params;
        if !(3..=MAX_WINDOW).contains(&window_px) || window_px % 2 == 0 {
            return Err(format!(
                "`window_px` must be odd and between 3 and {MAX_WINDOW}, got {window_px}"
            ));
        }
        check_pyramid_params(levels, scale)?;
        if !(1..=MAX_ITERATIONS).contains(&iterations) {
            return Err(format!(
                "`iterations` must be between 1 and {MAX_ITERATIONS}, got {iterations}"
            ));
        }
        if !min_eigenvalue.is_finite() || min_eigenvalue < 0.0 {
            return Err(format!(
                "`min_eigenvalue` must be finite and ≥ 0, got {min_eigenvalue}"
            ));
        }
        Ok(FlowLk {
            settings: LkSettings {
                window: window_px as usize,
                levels: levels as usize,
                scale,
                iterations: iterations as usize,
                min_eigenvalue: min_eigenvalue as f32,
            },
        })
    }
}

impl Operator for FlowLk {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        run_flow(inputs, |a, b| flow_lk(a, b, &self.settings))
    }
}

/// Window sum of a plane: the Gaussian of side `window` (σ from the side), reflect-101 border.
fn window_sum(data: Vec<f32>, w: usize, h: usize, window: usize) -> Result<Vec<f32>, String> {
    let image = Image::from_f32(w, h, Channels::Gray, data).map_err(|e| e.to_string())?;
    let out = gaussian_blur(
        &image,
        0.0,
        0.0,
        window,
        window,
        BorderMode::Reflect101,
        0.0,
    );
    Ok(plane_of(&out).data)
}

/// Dense Lucas–Kanade flow from `previous` to `next` (same size, any pixel format). See
/// [`FlowLkParams`] for the settings.
pub fn flow_lk(previous: &Image, next: &Image, settings: &LkSettings) -> Result<FlowField, String> {
    check_pair(previous, next)?;
    let (w, h) = (previous.width(), previous.height());
    if w == 0 || h == 0 {
        return Ok(FlowField::zeros(w, h));
    }
    let levels = flow_pyramid(previous, next, settings.levels, settings.scale)?;
    let win = settings.window.max(3) | 1;
    let mut flow: Option<FlowField> = None;
    for (li, level) in levels.iter().enumerate().rev() {
        let (lw, lh) = (level.prev.width, level.prev.height);
        let mut f = match (&flow, levels.get(li + 1)) {
            (Some(coarse), Some(map)) => upsample(coarse, lw, lh, map),
            _ => FlowField::zeros(lw, lh),
        };
        let (ix, iy) = gradients(&level.prev)?;
        let inverse = inverse_tensors(&ix, &iy, win, settings.min_eigenvalue)?;
        for _ in 0..settings.iterations {
            let warped = warp([&level.next], &f);
            let n = lw * lh;
            let mut bx = vec![0.0f32; n];
            let mut by = vec![0.0f32; n];
            bx.par_chunks_mut(BAND_ROWS * lw)
                .zip(by.par_chunks_mut(BAND_ROWS * lw))
                .enumerate()
                .for_each(|(band, (ox, oy))| {
                    let start = band * BAND_ROWS * lw;
                    for (k, (px, py)) in ox.iter_mut().zip(oy.iter_mut()).enumerate() {
                        let i = start + k;
                        let ([j], inside) = warped[i];
                        let t = if inside { j - level.prev.data[i] } else { 0.0 };
                        *px = ix.data[i] * t;
                        *py = iy.data[i] * t;
                    }
                });
            let bx = window_sum(bx, lw, lh, win)?;
            let by = window_sum(by, lw, lh, win)?;
            f.u.par_chunks_mut(BAND_ROWS * lw)
                .zip(f.v.par_chunks_mut(BAND_ROWS * lw))
                .enumerate()
                .for_each(|(band, (fu, fv))| {
                    let start = band * BAND_ROWS * lw;
                    for (k, (u, v)) in fu.iter_mut().zip(fv.iter_mut()).enumerate() {
                        let i = start + k;
                        let [a, b, c] = inverse[i];
                        *u -= a * bx[i] + b * by[i];
                        *v -= b * bx[i] + c * by[i];
                    }
                });
        }
        flow = Some(f);
    }
    Ok(flow.unwrap_or_else(|| FlowField::zeros(w, h)))
}

/// Per-pixel inverse `[i11, i12, i22]` of the window's structure tensor, zero where it is
/// ill-conditioned (smallest eigenvalue / 1024 below `min_eigenvalue`, or singular).
fn inverse_tensors(
    ix: &Plane,
    iy: &Plane,
    window: usize,
    min_eigenvalue: f32,
) -> Result<Vec<[f32; 3]>, String> {
    let (w, h) = (ix.width, ix.height);
    let product = |f: fn(f32, f32) -> f32| -> Vec<f32> {
        ix.data
            .iter()
            .zip(&iy.data)
            .map(|(&a, &b)| f(a, b))
            .collect()
    };
    let g11 = window_sum(product(|a, _| a * a), w, h, window)?;
    let g12 = window_sum(product(|a, b| a * b), w, h, window)?;
    let g22 = window_sum(product(|_, b| b * b), w, h, window)?;
    let mut out = vec![[0.0f32; 3]; w * h];
    out.par_chunks_mut(BAND_ROWS * w)
        .enumerate()
        .for_each(|(band, rows)| {
            let start = band * BAND_ROWS * w;
            for (k, o) in rows.iter_mut().enumerate() {
                let i = start + k;
                let (a, b, c) = (g11[i], g12[i], g22[i]);
                let min_eig = (a + c - ((a - c) * (a - c) + 4.0 * b * b).sqrt()) * 0.5 / 1024.0;
                let det = a * c - b * b;
                let weak = min_eig.is_nan() || min_eig < min_eigenvalue;
                if !weak && det.is_finite() && det > f32::EPSILON * (a + c).max(1.0) {
                    let inv = 1.0 / det;
                    *o = [c * inv, -b * inv, a * inv];
                }
            }
        });
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::video::flow::test_support::*;
    use ocellus_engine::value::{PixelData, Value};
    use proptest::prelude::*;

    fn lk(a: &Image, b: &Image) -> FlowField {
        flow_lk(a, b, &LkSettings::default()).unwrap()
    }

    #[test]
    fn sub_pixel_translation() {
        let (a, b, truth) = pair(160, 120, 7, translation(1.3, -0.7));
        let e = epe(&lk(&a, &b), &truth, 10);
        eprintln!("LK translation EPE {e}");
        assert!(e < 0.03, "EPE {e}");
    }

    #[test]
    fn small_rotation() {
        let (a, b, truth) = pair(160, 120, 8, rotation(2.0, 80.0, 60.0));
        let e = epe(&lk(&a, &b), &truth, 10);
        eprintln!("LK rotation EPE {e}");
        assert!(e < 0.03, "EPE {e}");
    }

    #[test]
    fn smooth_affine_field() {
        let map = [0.97, 0.015, 1.2, -0.01, 1.02, -0.8];
        let (a, b, truth) = pair(160, 120, 9, map);
        let e = epe(&lk(&a, &b), &truth, 10);
        eprintln!("LK affine EPE {e}");
        assert!(e < 0.03, "EPE {e}");
    }

    #[test]
    fn iterations_and_levels_buy_accuracy() {
        let (a, b, truth) = pair(128, 96, 4, translation(1.7, -1.1));
        let one = LkSettings {
            iterations: 1,
            ..LkSettings::default()
        };
        let e_one = epe(&flow_lk(&a, &b, &one).unwrap(), &truth, 10);
        let e_full = epe(&lk(&a, &b), &truth, 10);
        assert!(e_full < e_one, "{e_full} vs {e_one}");
        let (a, b, truth) = pair(128, 96, 4, translation(12.0, 7.0));
        let flat = LkSettings {
            levels: 0,
            ..LkSettings::default()
        };
        let e_flat = epe(&flow_lk(&a, &b, &flat).unwrap(), &truth, 10);
        let e_pyr = epe(&lk(&a, &b), &truth, 10);
        assert!(e_pyr < 0.1 && e_flat > 1.0, "{e_pyr} vs {e_flat}");
    }

    #[test]
    fn other_scale_factor() {
        let (a, b, truth) = pair(128, 96, 5, translation(-2.2, 1.4));
        let s = LkSettings {
            scale: 0.7,
            levels: 6,
            ..LkSettings::default()
        };
        let e = epe(&flow_lk(&a, &b, &s).unwrap(), &truth, 10);
        assert!(e < 0.04, "EPE {e}");
    }

    #[test]
    fn ill_conditioned_pixels_keep_the_coarser_flow() {
        // A textured frame with a flat vertical band (columns 40..88), all translated by
        // (2, 0): the band is at columns 42..90 in `next`.
        let (a, b, truth) = pair(128, 96, 3, translation(2.0, 0.0));
        let flatten = |im: &Image, from: usize| {
            let PixelData::F32(mut v) = im.clone().into_data() else {
                panic!()
            };
            for row in v.chunks_exact_mut(128) {
                row[from..from + 48].iter_mut().for_each(|s| *s = 0.5);
            }
            Image::from_f32(128, 96, Channels::Gray, v).unwrap()
        };
        let (a, b) = (flatten(&a, 40), flatten(&b, 42));
        let centre = 48 * 128 + 64;
        let textured = 48 * 128 + 20;
        // Without a pyramid there is no coarser flow: the band's centre stays at zero.
        let flat = LkSettings {
            levels: 0,
            ..LkSettings::default()
        };
        let f = flow_lk(&a, &b, &flat).unwrap();
        assert_eq!((f.u[centre], f.v[centre]), (0.0, 0.0));
        assert!((f.u[textured] - truth.u[textured]).abs() < 0.05);
        // With the pyramid the band's centre gets the coarse levels' flow, whose wider windows
        // reach the texture on both sides.
        let f = lk(&a, &b);
        assert!(f.u.iter().chain(&f.v).all(|x| x.is_finite()));
        assert!((f.u[centre] - 2.0).abs() < 0.5 && f.v[centre].abs() < 0.5);
        assert!((f.u[textured] - truth.u[textured]).abs() < 0.05);
        // The band's centre is never updated on the finest level: with the threshold at 0 the
        // (exactly singular) tensor there still gives no update.
        let all = LkSettings {
            min_eigenvalue: 0.0,
            ..LkSettings::default()
        };
        let g = flow_lk(&a, &b, &all).unwrap();
        assert!(g.u.iter().chain(&g.v).all(|x| x.is_finite()));
        assert_eq!((g.u[centre], g.v[centre]), (f.u[centre], f.v[centre]));
    }

    #[test]
    fn zero_motion_and_constant_frames() {
        let (a, _, _) = pair(64, 48, 3, IDENTITY);
        let f = lk(&a, &a);
        assert!(f.u.iter().chain(&f.v).all(|&x| x.abs() < 1e-6));
        let flat = Image::from_u8(40, 30, Channels::Gray, vec![90; 1200]).unwrap();
        let other = Image::from_u8(40, 30, Channels::Gray, vec![200; 1200]).unwrap();
        for (p, q) in [(&flat, &flat), (&flat, &other)] {
            let f = lk(p, q);
            assert!(f.u.iter().chain(&f.v).all(|&x| x == 0.0));
        }
    }

    #[test]
    fn tiny_empty_and_mismatched_frames() {
        for side in [1usize, 2, 3, 8] {
            let a = crate::filter::test_support::random_u8(side, side, Channels::Rgb, 3);
            let b = crate::filter::test_support::random_u8(side, side, Channels::Rgb, 4);
            let f = lk(&a, &b);
            assert_eq!(f.u.len(), side * side);
            assert!(f.u.iter().chain(&f.v).all(|x| x.is_finite()));
        }
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        assert!(lk(&empty, &empty).u.is_empty());
        let a = Image::from_u8(4, 4, Channels::Gray, vec![0; 16]).unwrap();
        let b = Image::from_u8(5, 4, Channels::Gray, vec![0; 20]).unwrap();
        assert!(flow_lk(&a, &b, &LkSettings::default()).is_err());
    }

    #[test]
    fn rgb_u8_frames() {
        let (a, b, truth) = pair(96, 72, 6, translation(0.8, 0.5));
        let to_rgb = |im: &Image| {
            let PixelData::F32(v) = im.data() else {
                panic!()
            };
            let d = v
                .iter()
                .flat_map(|&s| [(s * 255.0).round() as u8; 3])
                .collect();
            Image::from_u8(96, 72, Channels::Rgb, d).unwrap()
        };
        let e = epe(&lk(&to_rgb(&a), &to_rgb(&b)), &truth, 10);
        assert!(e < 0.06, "RGB u8 EPE {e}");
    }

    #[test]
    fn deterministic_across_thread_counts() {
        let (a, b, _) = pair(150, 100, 5, [1.01, 0.02, -1.7, -0.02, 1.0, 0.9]);
        let runs: Vec<FlowField> = [1, 2, 3]
            .iter()
            .map(|&n| {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(n)
                    .build()
                    .unwrap();
                pool.install(|| lk(&a, &b))
            })
            .collect();
        for r in &runs[1..] {
            assert_bit_identical(r, &runs[0]);
        }
    }

    #[test]
    fn operator_outputs_and_bad_params() {
        let op = FlowLk::new(FlowLkParams::default()).unwrap();
        assert_eq!(op.settings, LkSettings::default());
        for bad in [
            FlowLkParams {
                window_px: 14,
                ..Default::default()
            },
            FlowLkParams {
                window_px: 1,
                ..Default::default()
            },
            FlowLkParams {
                window_px: 103,
                ..Default::default()
            },
            FlowLkParams {
                levels: 17,
                ..Default::default()
            },
            FlowLkParams {
                scale: 0.1,
                ..Default::default()
            },
            FlowLkParams {
                iterations: 0,
                ..Default::default()
            },
            FlowLkParams {
                min_eigenvalue: f64::NAN,
                ..Default::default()
            },
            FlowLkParams {
                min_eigenvalue: -1.0,
                ..Default::default()
            },
        ] {
            assert!(FlowLk::new(bad).is_err());
        }
        let (a, b, _) = pair(48, 40, 2, translation(0.0, -1.0));
        let specs = FlowLk::inputs();
        let ctx = RunContext {
            node: "t".into(),
            threads: 1,
            element: None,
        };
        let values = vec![Some(Value::image(a)), Some(Value::image(b))];
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Image(v)) = out.take("v") else {
            panic!()
        };
        let PixelData::F32(vd) = v.data() else {
            panic!()
        };
        assert!((vd[20 * 48 + 24] + 1.0).abs() < 0.05);
        assert!(out.take("visualization").is_some() && out.take("u").is_some());
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(8))]
        #[test]
        fn random_translations(dx in -3.0f64..3.0, dy in -3.0f64..3.0, seed in 0u64..1000) {
            let (a, b, truth) = pair(80, 64, seed, translation(dx, dy));
            let e = epe(&lk(&a, &b), &truth, 10);
            prop_assert!(e < 0.05, "({dx}, {dy}): EPE {e}");
        }
    }
}
