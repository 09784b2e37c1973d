//! `video.flow_horn_schunck`: Horn–Schunck dense optical flow, coarse to fine with warping.
//!
//! [`flow_horn_schunck`] minimises the Horn & Schunck energy
//! `Σ (I_x du + I_y dv + I_t)² + α² (|∇u|² + |∇v|²)` for the flow increment `(du, dv)` around
//! the current flow on each pyramid level (the warped, incremental formulation of Brox et al.
//! 2004 / Sun, Roth & Black 2010 with a quadratic penalty). The linear Euler–Lagrange system is
//! solved by red–black SOR with a 2×2 block per pixel; after each warp the flow can be median
//! filtered.
//!
//! How it runs: each half-sweep updates the pixels of one colour from the other colour's values
//! only, on fixed row bands in parallel; every other pass is per pixel. Results are
//! bit-identical for any thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, Value};
use rayon::prelude::*;

use super::flow::{
    BAND_ROWS, FlowField, FlowLevel, check_pair, check_pyramid_params, flow_pyramid, flow_to_color,
    median_flow, upsample, warp,
};
use super::gray::gradients;

/// Largest `warps` and `iterations`.
pub const MAX_ITERATIONS: u32 = 10_000;

/// Largest median window, px.
pub const MAX_MEDIAN: u32 = 15;

params! {
    /// Parameters of `video.flow_horn_schunck`.
    pub struct FlowHornSchunckParams {
        /// Smoothness weight α, gray levels (frames on the 0–255 scale): the data term's
        /// residual is in gray levels, the smoothness term in px of flow per px, weighted by α².
        /// Larger is smoother (and blurs motion edges); > 0. Default 10.
        alpha: f64 = 10.0,
        /// Pyramid levels above the full-resolution one, 0..=16; levels with a side under 8 px
        /// are not built. Each level doubles (at scale 0.5) the largest motion that can be
        /// recovered. Default 5.
        levels: u32 = 5,
        /// Size ratio between successive pyramid levels, 0.25..=0.95; 0.5 uses `pyrDown`
        /// steps. Default 0.5.
        scale: f64 = 0.5,
        /// Warps (linearisations) per level, 1..=10000. Default 3.
        warps: u32 = 3,
        /// SOR iterations per warp, 1..=10000. Default 30.
        iterations: u32 = 30,
        /// SOR relaxation factor ω, in (0, 2); 1 is (red–black) Gauss–Seidel. Default 1.9.
        omega: f64 = 1.9,
        /// Side of the median filter applied to the flow after each warp, px, odd, 1..=15;
        /// 1 turns it off. Default 5.
        median_px: u32 = 5,
    }
}

/// Settings of one Horn–Schunck run (see [`FlowHornSchunckParams`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HsSettings {
    /// Smoothness weight α, gray levels.
    pub alpha: f32,
    /// Pyramid levels above the base.
    pub levels: usize,
    /// Pyramid scale factor.
    pub scale: f64,
    /// Warps per level.
    pub warps: usize,
    /// SOR iterations per warp.
    pub iterations: usize,
    /// SOR relaxation factor.
    pub omega: f32,
    /// Median window side (1: off).
    pub median: usize,
}

impl Default for HsSettings {
    fn default() -> Self {
        HsSettings {
            alpha: 10.0,
            levels: 5,
            scale: 0.5,
            warps: 3,
            iterations: 30,
            omega: 1.9,
            median: 5,
        }
    }
}

/// Horn–Schunck optical flow (`video.flow_horn_schunck`). See [`flow_horn_schunck`].
#[derive(Debug, Clone, PartialEq)]
pub struct FlowHornSchunck {
    settings: HsSettings,
}

impl Op for FlowHornSchunck {
    type Params = FlowHornSchunckParams;
    const ID: &'static str = "video.flow_horn_schunck";
    const SUMMARY: &'static str =
        "Dense optical flow by Horn–Schunck, coarse to fine with warping and SOR.";
    const DOC: &'static str = r#"
Estimates the motion of every pixel from `previous` to `next` with the global variational method
of Horn & Schunck, made practical for motions larger than a pixel the modern way (Brox et al.
2004; Sun, Roth & Black, "Secrets of optical flow estimation", 2010): coarse to fine over a
pyramid, re-linearising around the current flow by warping `next`.

Frames are converted to gray f32 on the 0–255 scale (u16 / 257, f32 · 255, RGB by BT.601
luma) and reduced into a pyramid (`levels` levels, each `scale` times smaller; 0.5 uses `pyrDown`,
other factors a Gaussian blur of σ = 1/√(2·scale) and bilinear resampling). Starting from zero on
the coarsest level, each level runs `warps` times: `next` is warped by the current flow `(u, v)`
(bicubic, Catmull–Rom: bilinear warping biases sub-pixel flow by a few hundredths of a px);
`I_t = next(x + u) − previous(x)`, and `I_x`, `I_y` are the mean of the Scharr
gradients of `previous` and of the warped gradients of `next`. The increment `(du, dv)` then
minimises `Σ (I_x du + I_y dv + I_t)² + α² Σ (|∇(u + du)|² + |∇(v + dv)|²)` (4-neighbour
differences, no smoothing across the frame edge); its linear Euler–Lagrange equations are solved
by `iterations` sweeps of red–black SOR (each pixel's 2×2 system solved exactly, relaxed by
`omega`). Pixels whose warped position leaves the frame drop their data term and are filled in by
the smoothness term. After each warp the flow is median filtered (`median_px`, as in Sun et al.'s
"Classic+"; this removes outliers and keeps motion edges sharper). The flow of a level, resampled
and scaled, starts the next finer one.

Outputs: `u` and `v`, gray f32 images with the flow in px (the content at (x, y) in `previous` is
at (x + u, y + v) in `next`), the convention of `video.block_match` and of `filter.lic`'s `vx` /
`vy`; `visualization`, RGB u8, the Middlebury colour coding (Baker et al. 2011: hue = direction,
saturation = length relative to the largest in the field, white = still).

Speed and accuracy: time grows linearly with `warps × iterations` (and the pixel count). More
`levels` recover larger motions (about 2^levels px at scale 0.5) at little cost; a larger
`scale` (e.g. 0.8) gives more, closer levels, which is slower but more robust for large or
non-rigid motion. More `warps` refine sub-pixel accuracy (the linearisation is only valid for
small increments); more `iterations` let the smoothness term propagate further, which matters
in weakly textured regions. `alpha` trades detail for smoothness. The quadratic penalties make
motion boundaries blurry and outliers spread; the median filter is the cheap remedy.

Differences: OpenCV's main module has no Horn–Schunck (`cv::optflow` in the contrib modules has
DeepFlow / variational refinement with robust penalties, not this quadratic model). Frames are
not presmoothed.

References: B. K. P. Horn, B. G. Schunck, "Determining optical flow", Artificial Intelligence 17,
1981; T. Brox, A. Bruhn, N. Papenberg, J. Weickert, "High accuracy optical flow estimation based
on a theory for warping", ECCV 2004; D. Sun, S. Roth, M. J. Black, "Secrets of optical flow
estimation and their principles", CVPR 2010; S. Baker et al., "A database and evaluation
methodology for optical flow", IJCV 2011.

Example:
    "flow": (op: "video.flow_horn_schunck", inputs: { "previous": "a.image", "next": "b.image" }, params: (alpha: 10.0, levels: 5, warps: 3, iterations: 30)),
"#;

    fn inputs() -> Vec<PortSpec> {
        flow_inputs()
    }

    fn outputs() -> Vec<PortSpec> {
        flow_outputs()
    }

    fn new(params: FlowHornSchunckParams) -> Result<Self, String> {
        let FlowHornSchunckParams {
            alpha,
            levels,
            scale,
            warps,
            iterations,
            omega,
            median_px,
        } = params;
        if !alpha.is_finite() || alpha <= 0.0 || alpha > 1e6 {
            return Err(format!("`alpha` must be in (0, 1e6], got {alpha}"));
        }
        check_pyramid_params(levels, scale)?;
        for (name, v) in [("warps", warps), ("iterations", iterations)] {
            if !(1..=MAX_ITERATIONS).contains(&v) {
                return Err(format!(
                    "`{name}` must be between 1 and {MAX_ITERATIONS}, got {v}"
                ));
            }
        }
        if !omega.is_finite() || omega <= 0.0 || omega >= 2.0 {
            return Err(format!("`omega` must be in (0, 2), got {omega}"));
        }
        if !(1..=MAX_MEDIAN).contains(&median_px) || median_px % 2 == 0 {
            return Err(format!(
                "`median_px` must be odd and between 1 and {MAX_MEDIAN}, got {median_px}"
            ));
        }
        Ok(FlowHornSchunck {
            settings: HsSettings {
                alpha: alpha as f32,
                levels: levels as usize,
                scale,
                warps: warps as usize,
                iterations: iterations as usize,
                omega: omega as f32,
                median: median_px as usize,
            },
        })
    }
}

/// Input ports shared by the dense flow operators.
pub(crate) fn flow_inputs() -> Vec<PortSpec> {
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
    ]
}

/// Output ports shared by the dense flow operators.
pub(crate) fn flow_outputs() -> Vec<PortSpec> {
    vec![
        PortSpec::new("u", PortType::Image, "Horizontal flow, px, gray f32."),
        PortSpec::new("v", PortType::Image, "Vertical flow, px, gray f32."),
        PortSpec::new(
            "visualization",
            PortType::Image,
            "Middlebury colour coding of the flow, RGB u8.",
        ),
    ]
}

/// Runs a dense flow function on the operator's inputs and packs its outputs.
pub(crate) fn run_flow(
    inputs: &Inputs<'_>,
    compute: impl FnOnce(&Image, &Image) -> Result<FlowField, String>,
) -> Result<Outputs, OpError> {
    let previous = inputs.image("previous")?;
    let next = inputs.image("next")?;
    check_pair(previous, next).map_err(|e| OpError::input("next", e))?;
    let flow = compute(previous, next).map_err(OpError::failed)?;
    let (u, v) = flow.to_images().map_err(OpError::failed)?;
    let colour = flow_to_color(&flow).map_err(OpError::failed)?;
    Ok(Outputs::new()
        .with("u", Value::image(u))
        .with("v", Value::image(v))
        .with("visualization", Value::image(colour)))
}

impl Operator for FlowHornSchunck {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        run_flow(inputs, |a, b| flow_horn_schunck(a, b, &self.settings))
    }
}

/// Horn–Schunck flow from `previous` to `next` (same size, any pixel format). See
/// [`FlowHornSchunckParams`] for the settings.
pub fn flow_horn_schunck(
    previous: &Image,
    next: &Image,
    settings: &HsSettings,
) -> Result<FlowField, String> {
    check_pair(previous, next)?;
    let (w, h) = (previous.width(), previous.height());
    if w == 0 || h == 0 {
        return Ok(FlowField::zeros(w, h));
    }
    let levels = flow_pyramid(previous, next, settings.levels, settings.scale)?;
    let alpha2 = settings.alpha * settings.alpha;
    let mut flow: Option<FlowField> = None;
    for (li, level) in levels.iter().enumerate().rev() {
        let (lw, lh) = (level.prev.width, level.prev.height);
        let mut f = match (&flow, levels.get(li + 1)) {
            (Some(coarse), Some(map)) => upsample(coarse, lw, lh, map),
            _ => FlowField::zeros(lw, lh),
        };
        for _ in 0..settings.warps {
            let system = linearise(level, &f, alpha2)?;
            let (du, dv) = solve(&system, lw, lh, settings.iterations, settings.omega);
            for (a, d) in f.u.iter_mut().zip(&du) {
                *a += d;
            }
            for (a, d) in f.v.iter_mut().zip(&dv) {
                *a += d;
            }
            f = median_flow(&f, settings.median)?;
        }
        flow = Some(f);
    }
    Ok(flow.unwrap_or_else(|| FlowField::zeros(w, h)))
}

/// Per-pixel coefficients of the increment's equations, divided by α²: `[i11, i12, i22, c1, c2]`
/// with `(du, dv) = [[i11, i12], [i12, i22]] · (c1 + Σ du_n, c2 + Σ dv_n)` (Gauss–Seidel value).
type Coefficients = [f32; 5];

/// The linearised system around `flow` on one level.
fn linearise(
    level: &FlowLevel,
    flow: &FlowField,
    alpha2: f32,
) -> Result<Vec<Coefficients>, String> {
    let (w, h) = (flow.width, flow.height);
    let (ix, iy) = gradients(&level.prev)?;
    let (jx, jy) = gradients(&level.next)?;
    let warped = warp([&level.next, &jx, &jy], flow);
    let mut out = vec![[0.0f32; 5]; w * h];
    let inv_a2 = 1.0 / alpha2;
    out.par_chunks_mut(BAND_ROWS * w)
        .enumerate()
        .for_each(|(band, rows)| {
            for (r, row) in rows.chunks_exact_mut(w).enumerate() {
                let y = band * BAND_ROWS + r;
                for (x, c) in row.iter_mut().enumerate() {
                    let i = y * w + x;
                    let ([j, jwx, jwy], inside) = warped[i];
                    let (gx, gy, gt) = if inside {
                        (
                            0.5 * (ix.data[i] + jwx),
                            0.5 * (iy.data[i] + jwy),
                            j - level.prev.data[i],
                        )
                    } else {
                        (0.0, 0.0, 0.0)
                    };
                    // Neighbour count and Σ (u0_n − u0) over the in-frame 4-neighbours.
                    let mut n = 0.0f32;
                    let (mut lu, mut lv) = (0.0f32, 0.0f32);
                    let mut add = |k: usize| {
                        n += 1.0;
                        lu += flow.u[k] - flow.u[i];
                        lv += flow.v[k] - flow.v[i];
                    };
                    if x > 0 {
                        add(i - 1);
                    }
                    if x + 1 < w {
                        add(i + 1);
                    }
                    if y > 0 {
                        add(i - w);
                    }
                    if y + 1 < h {
                        add(i + w);
                    }
                    // A = (∇I ∇Iᵀ)/α² + n·Id, b = −∇I·I_t/α² + Σ (u0_n − u0).
                    let a11 = gx * gx * inv_a2 + n;
                    let a12 = gx * gy * inv_a2;
                    let a22 = gy * gy * inv_a2 + n;
                    let det = a11 * a22 - a12 * a12;
                    if det > 0.0 && det.is_finite() {
                        let inv = 1.0 / det;
                        *c = [
                            a22 * inv,
                            -a12 * inv,
                            a11 * inv,
                            -gx * gt * inv_a2 + lu,
                            -gy * gt * inv_a2 + lv,
                        ];
                    }
                }
            }
        });
    Ok(out)
}

/// Red–black SOR on the increment: `iterations` sweeps, each a red half-sweep ((x + y) even)
/// then a black one, starting from zero.
fn solve(
    system: &[Coefficients],
    w: usize,
    h: usize,
    iterations: usize,
    omega: f32,
) -> (Vec<f32>, Vec<f32>) {
    let mut cur = (vec![0.0f32; w * h], vec![0.0f32; w * h]);
    let mut nxt = (vec![0.0f32; w * h], vec![0.0f32; w * h]);
    for _ in 0..iterations {
        for parity in 0..2 {
            let (cu, cv) = (&cur.0, &cur.1);
            nxt.0
                .par_chunks_mut(BAND_ROWS * w)
                .zip(nxt.1.par_chunks_mut(BAND_ROWS * w))
                .enumerate()
                .for_each(|(band, (bu, bv))| {
                    for (r, (ou, ov)) in bu
                        .chunks_exact_mut(w)
                        .zip(bv.chunks_exact_mut(w))
                        .enumerate()
                    {
                        let y = band * BAND_ROWS + r;
                        relax_row(system, cu, cv, ou, ov, w, h, y, parity, omega);
                    }
                });
            std::mem::swap(&mut cur, &mut nxt);
        }
    }
    cur
}

/// One row of a half-sweep: pixels with `(x + y) % 2 == parity` are relaxed from their
/// neighbours in `cu`, `cv`; the others are copied.
#[allow(clippy::too_many_arguments)]
#[inline]
fn relax_row(
    system: &[Coefficients],
    cu: &[f32],
    cv: &[f32],
    ou: &mut [f32],
    ov: &mut [f32],
    w: usize,
    h: usize,
    y: usize,
    parity: usize,
    omega: f32,
) {
    let row = y * w;
    ou.copy_from_slice(&cu[row..row + w]);
    ov.copy_from_slice(&cv[row..row + w]);
    let first = (parity + y) & 1;
    // Rows above and below (an absent one reads as zeros: its coefficient is not counted).
    let zeros = [0.0f32; 0];
    let (uu, uv) = if y > 0 {
        (&cu[row - w..row], &cv[row - w..row])
    } else {
        (&zeros[..], &zeros[..])
    };
    let (du, dv) = if y + 1 < h {
        (&cu[row + w..row + 2 * w], &cv[row + w..row + 2 * w])
    } else {
        (&zeros[..], &zeros[..])
    };
    let (ru, rv) = (&cu[row..row + w], &cv[row..row + w]);
    let coef = &system[row..row + w];
    let vertical = |x: usize| -> (f32, f32) {
        let mut s = (0.0, 0.0);
        if let (Some(a), Some(b)) = (uu.get(x), uv.get(x)) {
            s.0 += a;
            s.1 += b;
        }
        if let (Some(a), Some(b)) = (du.get(x), dv.get(x)) {
            s.0 += a;
            s.1 += b;
        }
        s
    };
    let mut update = |x: usize, su: f32, sv: f32| {
        let k = &coef[x];
        let r1 = k[3] + su;
        let r2 = k[4] + sv;
        let gu = k[0] * r1 + k[1] * r2;
        let gv = k[1] * r1 + k[2] * r2;
        ou[x] = ru[x] + omega * (gu - ru[x]);
        ov[x] = rv[x] + omega * (gv - rv[x]);
    };
    let full = !uu.is_empty() && !du.is_empty();
    for x in (first..w).step_by(2) {
        let (mut su, mut sv) = if full {
            (uu[x] + du[x], uv[x] + dv[x])
        } else {
            vertical(x)
        };
        if x > 0 {
            su += ru[x - 1];
            sv += rv[x - 1];
        }
        if x + 1 < w {
            su += ru[x + 1];
            sv += rv[x + 1];
        }
        update(x, su, sv);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::video::flow::test_support::*;
    use ocellus_engine::value::{Channels, PixelData};
    use proptest::prelude::*;

    fn hs(a: &Image, b: &Image) -> FlowField {
        flow_horn_schunck(a, b, &HsSettings::default()).unwrap()
    }

    #[test]
    fn sub_pixel_translation() {
        let (a, b, truth) = pair(160, 120, 7, translation(1.3, -0.7));
        let e = epe(&hs(&a, &b), &truth, 10);
        eprintln!("HS translation EPE {e}");
        assert!(e < 0.02, "EPE {e}");
    }

    #[test]
    fn small_rotation() {
        let (a, b, truth) = pair(160, 120, 8, rotation(2.0, 80.0, 60.0));
        let e = epe(&hs(&a, &b), &truth, 10);
        eprintln!("HS rotation EPE {e}");
        assert!(e < 0.02, "EPE {e}");
    }

    #[test]
    fn smooth_affine_field() {
        // Zoom by 3 %, shear and a shift: flow up to ~3.5 px.
        let map = [0.97, 0.015, 1.2, -0.01, 1.02, -0.8];
        let (a, b, truth) = pair(160, 120, 9, map);
        let e = epe(&hs(&a, &b), &truth, 10);
        eprintln!("HS affine EPE {e}");
        assert!(e < 0.02, "EPE {e}");
    }

    #[test]
    fn more_warps_and_iterations_buy_accuracy() {
        let (a, b, truth) = pair(128, 96, 4, rotation(3.0, 64.0, 48.0));
        let cheap = HsSettings {
            warps: 1,
            iterations: 5,
            ..HsSettings::default()
        };
        let e_cheap = epe(&flow_horn_schunck(&a, &b, &cheap).unwrap(), &truth, 10);
        let e_full = epe(&hs(&a, &b), &truth, 10);
        assert!(e_full < e_cheap, "{e_full} vs {e_cheap}");
        // Without the pyramid a 12 px motion is out of reach.
        let (a, b, truth) = pair(128, 96, 4, translation(12.0, 7.0));
        let flat = HsSettings {
            levels: 0,
            ..HsSettings::default()
        };
        let e_flat = epe(&flow_horn_schunck(&a, &b, &flat).unwrap(), &truth, 10);
        let e_pyr = epe(&hs(&a, &b), &truth, 10);
        assert!(e_pyr < 0.1 && e_flat > 1.0, "{e_pyr} vs {e_flat}");
    }

    #[test]
    fn other_scale_factor() {
        let (a, b, truth) = pair(128, 96, 5, translation(-2.2, 1.4));
        let s = HsSettings {
            scale: 0.7,
            levels: 6,
            ..HsSettings::default()
        };
        let e = epe(&flow_horn_schunck(&a, &b, &s).unwrap(), &truth, 10);
        assert!(e < 0.03, "EPE {e}");
    }

    #[test]
    fn zero_motion_and_constant_frames() {
        let (a, _, _) = pair(64, 48, 3, IDENTITY);
        let f = hs(&a, &a);
        assert!(f.u.iter().chain(&f.v).all(|&x| x.abs() < 1e-6));
        let flat = Image::from_u8(40, 30, Channels::Gray, vec![90; 1200]).unwrap();
        let other = Image::from_u8(40, 30, Channels::Gray, vec![200; 1200]).unwrap();
        for (p, q) in [(&flat, &flat), (&flat, &other)] {
            let f = hs(p, q);
            assert!(f.u.iter().chain(&f.v).all(|&x| x == 0.0));
        }
    }

    #[test]
    fn tiny_empty_and_mismatched_frames() {
        for side in [1usize, 2, 3, 8] {
            let a = crate::filter::test_support::random_u8(side, side, Channels::Rgb, 3);
            let b = crate::filter::test_support::random_u8(side, side, Channels::Rgb, 4);
            let f = hs(&a, &b);
            assert_eq!(f.u.len(), side * side);
            assert!(f.u.iter().chain(&f.v).all(|x| x.is_finite()));
        }
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        assert!(hs(&empty, &empty).u.is_empty());
        let a = Image::from_u8(4, 4, Channels::Gray, vec![0; 16]).unwrap();
        let b = Image::from_u8(4, 5, Channels::Gray, vec![0; 20]).unwrap();
        assert!(flow_horn_schunck(&a, &b, &HsSettings::default()).is_err());
    }

    #[test]
    fn pixel_formats_agree() {
        let (a, b, truth) = pair(96, 72, 6, translation(0.8, 0.5));
        let to_u16 = |im: &Image| {
            let PixelData::F32(v) = im.data() else {
                panic!()
            };
            let d = v.iter().map(|&s| (s * 65535.0).round() as u16).collect();
            Image::from_u16(96, 72, Channels::Gray, d).unwrap()
        };
        let e = epe(&hs(&to_u16(&a), &to_u16(&b)), &truth, 10);
        assert!(e < 0.05, "u16 EPE {e}");
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
                pool.install(|| hs(&a, &b))
            })
            .collect();
        for r in &runs[1..] {
            assert_bit_identical(r, &runs[0]);
        }
    }

    #[test]
    fn operator_outputs_and_bad_params() {
        let op = FlowHornSchunck::new(FlowHornSchunckParams::default()).unwrap();
        assert_eq!(op.settings, HsSettings::default());
        for bad in [
            FlowHornSchunckParams {
                alpha: 0.0,
                ..Default::default()
            },
            FlowHornSchunckParams {
                alpha: f64::NAN,
                ..Default::default()
            },
            FlowHornSchunckParams {
                levels: 17,
                ..Default::default()
            },
            FlowHornSchunckParams {
                scale: 1.0,
                ..Default::default()
            },
            FlowHornSchunckParams {
                warps: 0,
                ..Default::default()
            },
            FlowHornSchunckParams {
                iterations: 0,
                ..Default::default()
            },
            FlowHornSchunckParams {
                omega: 2.0,
                ..Default::default()
            },
            FlowHornSchunckParams {
                median_px: 4,
                ..Default::default()
            },
        ] {
            assert!(FlowHornSchunck::new(bad).is_err());
        }
        let (a, b, _) = pair(48, 40, 2, translation(1.0, 0.0));
        let specs = FlowHornSchunck::inputs();
        let ctx = RunContext {
            node: "t".into(),
            threads: 1,
            element: None,
        };
        let values = vec![Some(Value::image(a.clone())), Some(Value::image(b))];
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Image(u)) = out.take("u") else {
            panic!()
        };
        let PixelData::F32(ud) = u.data() else {
            panic!()
        };
        assert!((ud[20 * 48 + 24] - 1.0).abs() < 0.05);
        let Some(Value::Image(vis)) = out.take("visualization") else {
            panic!()
        };
        assert_eq!((vis.width(), vis.channels()), (48, Channels::Rgb));
        let small = Image::from_u8(4, 4, Channels::Gray, vec![0; 16]).unwrap();
        let values = vec![Some(Value::image(a)), Some(Value::image(small))];
        let err = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap_err();
        assert!(err.to_string().contains("next"), "{err}");
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(8))]
        #[test]
        fn random_translations(dx in -3.0f64..3.0, dy in -3.0f64..3.0, seed in 0u64..1000) {
            let (a, b, truth) = pair(80, 64, seed, translation(dx, dy));
            let e = epe(&hs(&a, &b), &truth, 10);
            prop_assert!(e < 0.05, "({dx}, {dy}): EPE {e}");
        }
    }
}
