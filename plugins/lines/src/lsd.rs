//! LSD: a Line Segment Detector.
//!
//! Implements the method of R. Grompone von Gioi, J. Jakubowicz, J.-M. Morel
//! and G. Randall, "LSD: a Line Segment Detector", Image Processing On Line 2
//! (2012), and "LSD: A Fast Line Segment Detector with a False Detection
//! Control", IEEE PAMI 32(4), 2010:
//!
//! 1. Gaussian subsampling by `scale` (kernel σ = `sigma_scale / scale` when
//!    `scale < 1`, `sigma_scale` otherwise; symmetric border),
//! 2. gradient on 2×2 windows, level-line angles, magnitude threshold
//!    `ρ = quant / sin(τ)`,
//! 3. pseudo-ordering of the pixels by gradient magnitude in `bins` bins,
//! 4. region growing (8-connectivity) with angle tolerance `τ`,
//! 5. rectangle approximation (magnitude-weighted centre of mass and principal
//!    inertia axis),
//! 6. a-contrario validation: `NFA = N_T · B(n, k, p)` with
//!    `N_T = 11·(X·Y)^{5/2}` and the binomial tail evaluated through the
//!    log-gamma function (Lanczos approximation for `x ≤ 15`, Windschitl's
//!    approximation above, as in the paper),
//! 7. refinement: density check, re-growing with a tolerance estimated from
//!    the pixels near the seed, region radius reduction, and the rectangle
//!    improvement steps (precision halving, width reduction, side shifts,
//!    precision halving again).
//!
//! # Coordinates
//! Segment coordinates are in the input image's pixel coordinates with pixel
//! centres at integer coordinates: pixel `(0, 0)` covers `[-0.5, 0.5]²`, `x`
//! grows to the right and `y` downwards. A vertical step edge between columns
//! 59 and 60 is reported at `x = 59.5`. (Internally, the gradient of the 2×2
//! window whose top-left pixel is `(x, y)` lives at `(x + 0.5, y + 0.5)` of
//! the subsampled image, and subsampled pixel `u` maps to input `u / scale`.)
//!
//! Simplifications: when the number of aligned points `k` does not exceed
//! its expectation `n·p`, the binomial tail is taken as 1 (it lies in
//! `[~0.5, 1]`, never meaningful); the binomial tail sum stops at a relative
//! error of 1e-9. Pixels with non-finite values are rejected with an error.
//! The implementation is single-threaded and deterministic.

#![deny(clippy::unwrap_used, clippy::expect_used)]

use std::f64::consts::{LN_10, PI};

/// Parameters of [`detect_segments`] (defaults are those of the paper).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LsdParams {
    /// Subsampling factor of the Gaussian pre-filter (0.8; 1.0 disables it).
    pub scale: f64,
    /// Gaussian σ is `sigma_scale / scale` (0.6).
    pub sigma_scale: f64,
    /// Bound on the quantization error of the gradient norm (2.0, gray levels).
    pub quant: f64,
    /// Angle tolerance τ in degrees (22.5), in `(0, 180)`.
    pub angle_tolerance_deg: f64,
    /// Detection threshold: segments with `−log10(NFA) > log_eps` are kept (0.0).
    pub log_eps: f64,
    /// Minimal density of region points in the rectangle, in `[0, 1]` (0.7).
    pub density_threshold: f64,
    /// Number of bins of the gradient-magnitude pseudo-ordering (1024).
    pub bins: usize,
}

impl Default for LsdParams {
    fn default() -> Self {
        Self {
            scale: 0.8,
            sigma_scale: 0.6,
            quant: 2.0,
            angle_tolerance_deg: 22.5,
            log_eps: 0.0,
            density_threshold: 0.7,
            bins: 1024,
        }
    }
}

impl LsdParams {
    /// Checks the parameters.
    ///
    /// # Errors
    /// A description of the first invalid parameter: `scale` or
    /// `sigma_scale` not finite and positive, negative or non-finite `quant`,
    /// `angle_tolerance_deg` outside `(0, 180)`, non-finite `log_eps`,
    /// `density_threshold` outside `[0, 1]`, or `bins == 0`.
    pub fn validate(&self) -> Result<(), String> {
        if !self.scale.is_finite() || self.scale <= 0.0 {
            return Err(format!("scale must be finite and > 0, got {}", self.scale));
        }
        if !self.sigma_scale.is_finite() || self.sigma_scale <= 0.0 {
            return Err(format!(
                "sigma_scale must be finite and > 0, got {}",
                self.sigma_scale
            ));
        }
        if !self.quant.is_finite() || self.quant < 0.0 {
            return Err(format!("quant must be finite and >= 0, got {}", self.quant));
        }
        if !self.angle_tolerance_deg.is_finite()
            || self.angle_tolerance_deg <= 0.0
            || self.angle_tolerance_deg >= 180.0
        {
            return Err(format!(
                "angle_tolerance_deg must be in (0, 180), got {}",
                self.angle_tolerance_deg
            ));
        }
        if !self.log_eps.is_finite() {
            return Err(format!("log_eps must be finite, got {}", self.log_eps));
        }
        if !(0.0..=1.0).contains(&self.density_threshold) {
            return Err(format!(
                "density_threshold must be in [0, 1], got {}",
                self.density_threshold
            ));
        }
        if self.bins == 0 {
            return Err("bins must be >= 1".to_string());
        }
        Ok(())
    }
}

/// A detected line segment (input image pixel coordinates, see the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Segment {
    /// First endpoint, x.
    pub x1: f64,
    /// First endpoint, y.
    pub y1: f64,
    /// Second endpoint, x.
    pub x2: f64,
    /// Second endpoint, y.
    pub y2: f64,
    /// Width of the supporting rectangle, in input pixels.
    pub width: f64,
    /// Angle precision `p` (probability that a random pixel is aligned), `τ/π` or finer.
    pub p: f64,
    /// `−log10(NFA)`: larger is more meaningful.
    pub log_nfa: f64,
}

/// Largest number of pixels of the (subsampled) working image.
const MAX_PIXELS: f64 = (1u64 << 31) as f64;
/// Iteration cap of the binomial tail sum.
const MAX_TAIL_TERMS: u64 = 1_000_000;

/// Detects line segments in a gray image.
///
/// `gray` holds `width * height` values (typically 0..255, e.g. `u8` converted
/// to `f64`), row-major. Segments are returned in detection order with
/// coordinates in input pixels (pixel centres at integers). An empty image
/// gives an empty result.
///
/// # Errors
/// Invalid parameters (see [`LsdParams::validate`]), a buffer size mismatch,
/// non-finite pixel values, or a subsampled image too large to allocate.
pub fn detect_segments(
    gray: &[f64],
    width: usize,
    height: usize,
    p: &LsdParams,
) -> Result<Vec<Segment>, String> {
    p.validate()?;
    let n = width
        .checked_mul(height)
        .ok_or_else(|| "image size overflows".to_string())?;
    if gray.len() != n {
        return Err(format!(
            "buffer size mismatch: expected {n} values ({width}x{height}), got {}",
            gray.len()
        ));
    }
    if n == 0 {
        return Ok(Vec::new());
    }
    if gray.iter().any(|v| !v.is_finite()) {
        return Err("image contains non-finite values".to_string());
    }

    let (img, sw, sh) = if p.scale != 1.0 {
        gaussian_subsample(gray, width, height, p.scale, p.sigma_scale)?
    } else {
        (gray.to_vec(), width, height)
    };
    if sw < 2 || sh < 2 {
        return Ok(Vec::new());
    }

    let prec = p.angle_tolerance_deg.to_radians();
    let pr = p.angle_tolerance_deg / 180.0;
    let rho = p.quant / prec.sin();
    let grad = Gradient::new(&img, sw, sh, rho);
    let log_nt = 5.0 * ((sw as f64).log10() + (sh as f64).log10()) / 2.0 + 11f64.log10();
    let min_reg_size = (-log_nt / pr.log10()).max(0.0) as usize;

    let order = pseudo_order(&grad, p.bins);
    let mut used = vec![false; sw * sh];
    let mut reg: Vec<(usize, usize)> = Vec::new();
    let mut out = Vec::new();
    let ctx = Ctx {
        g: &grad,
        log_nt,
        log_eps: p.log_eps,
        density_th: p.density_threshold,
    };

    for &seed in &order {
        if used.get(seed).copied().unwrap_or(true) {
            continue;
        }
        let seed_xy = (seed % sw, seed / sw);
        let reg_angle = region_grow(seed_xy, &grad, &mut used, prec, &mut reg);
        if reg.len() < min_reg_size {
            continue;
        }
        let mut rect = region2rect(&reg, &grad, reg_angle, prec, pr);
        if !ctx.refine(&mut reg, &mut rect, &mut used, prec, pr, seed_xy) {
            continue;
        }
        let log_nfa = ctx.rect_improve(&mut rect);
        if log_nfa <= p.log_eps {
            continue;
        }
        let s = 1.0 / p.scale;
        let coords = [rect.x1, rect.y1, rect.x2, rect.y2, rect.width, log_nfa];
        if coords.iter().any(|v| !v.is_finite()) {
            continue;
        }
        out.push(Segment {
            x1: (rect.x1 + 0.5) * s,
            y1: (rect.y1 + 0.5) * s,
            x2: (rect.x2 + 0.5) * s,
            y2: (rect.y2 + 0.5) * s,
            width: rect.width * s,
            p: rect.p,
            log_nfa,
        });
    }
    Ok(out)
}

/// Draws segments in red (1 px, no anti-aliasing) onto an RGB copy of the
/// gray image (values clamped to 0..255 and rounded). Returns
/// `width * height * 3` bytes; missing input values are drawn black.
pub fn draw_segments(gray: &[f64], width: usize, height: usize, segments: &[Segment]) -> Vec<u8> {
    let Some(n) = width.checked_mul(height).and_then(|n| n.checked_mul(3)) else {
        return Vec::new();
    };
    let mut rgb = vec![0u8; n];
    for (i, px) in rgb.chunks_exact_mut(3).enumerate() {
        let v = gray.get(i).copied().unwrap_or(0.0);
        let v = if v.is_finite() {
            v.round().clamp(0.0, 255.0) as u8
        } else {
            0
        };
        px.fill(v);
    }
    for s in segments {
        let Some((ax, ay, bx, by)) = clip_segment(
            s.x1,
            s.y1,
            s.x2,
            s.y2,
            width as f64 - 0.5,
            height as f64 - 0.5,
        ) else {
            continue;
        };
        let steps = (bx - ax).abs().max((by - ay).abs()).ceil().max(1.0);
        let steps = steps.min(4.0 * (width as f64 + height as f64) + 4.0) as usize;
        for i in 0..=steps {
            let t = i as f64 / steps as f64;
            let x = (ax + t * (bx - ax)).round();
            let y = (ay + t * (by - ay)).round();
            if x < 0.0 || y < 0.0 || x >= width as f64 || y >= height as f64 {
                continue;
            }
            let idx = (y as usize * width + x as usize) * 3;
            if let Some(px) = rgb.get_mut(idx..idx + 3) {
                px.copy_from_slice(&[255, 0, 0]);
            }
        }
    }
    rgb
}

/// Clips a segment to `[-0.5, xmax] × [-0.5, ymax]` (Liang–Barsky).
fn clip_segment(
    x1: f64,
    y1: f64,
    x2: f64,
    y2: f64,
    xmax: f64,
    ymax: f64,
) -> Option<(f64, f64, f64, f64)> {
    if ![x1, y1, x2, y2].iter().all(|v| v.is_finite()) {
        return None;
    }
    let (dx, dy) = (x2 - x1, y2 - y1);
    let mut t0 = 0.0f64;
    let mut t1 = 1.0f64;
    for (pk, qk) in [
        (-dx, x1 + 0.5),
        (dx, xmax - x1),
        (-dy, y1 + 0.5),
        (dy, ymax - y1),
    ] {
        if pk == 0.0 {
            if qk < 0.0 {
                return None;
            }
        } else {
            let r = qk / pk;
            if pk < 0.0 {
                t0 = t0.max(r);
            } else {
                t1 = t1.min(r);
            }
        }
    }
    if t0 > t1 {
        return None;
    }
    Some((x1 + t0 * dx, y1 + t0 * dy, x1 + t1 * dx, y1 + t1 * dy))
}

/// Natural logarithm of the gamma function for `x > 0`: Lanczos
/// approximation for `x ≤ 15`, Windschitl's approximation above (as in the
/// LSD paper). Returns `+∞` for `x ≤ 0` or non-finite `x`.
pub fn log_gamma(x: f64) -> f64 {
    if x.is_nan() || x <= 0.0 || x.is_infinite() {
        return f64::INFINITY;
    }
    if x > 15.0 {
        log_gamma_windschitl(x)
    } else {
        log_gamma_lanczos(x)
    }
}

/// Lanczos approximation of `ln Γ(x)` (coefficients as given in the LSD paper).
fn log_gamma_lanczos(x: f64) -> f64 {
    const Q: [f64; 7] = [
        75_122.633_153,
        80_916.627_895_2,
        36_308.295_147_7,
        8_687.245_297_05,
        1_168.926_494_79,
        83.867_604_342_4,
        2.506_628_275_11,
    ];
    let mut num = 0.0;
    let mut xn = 1.0;
    let mut den = 0.0;
    for (n, q) in Q.iter().enumerate() {
        num += q * xn;
        xn *= x;
        den += (x + n as f64).ln();
    }
    num.ln() - den + (x + 0.5) * (x + 5.5).ln() - (x + 5.5)
}

/// Windschitl's approximation of `ln Γ(x)`, accurate for large `x`.
fn log_gamma_windschitl(x: f64) -> f64 {
    0.5 * (2.0 * PI).ln() + (x - 0.5) * x.ln() - x
        + 0.5 * x * (x * (1.0 / x).sinh() + 1.0 / (810.0 * x.powi(6))).ln()
}

/// `−log10(NFA)` with `NFA = 10^log_nt · Σ_{j=k}^{n} C(n, j) p^j (1 − p)^{n−j}`.
fn nfa(n: u64, k: u64, p: f64, log_nt: f64) -> f64 {
    if n == 0 || k == 0 || k > n || !(p > 0.0 && p < 1.0) {
        return -log_nt;
    }
    let (nf, kf) = (n as f64, k as f64);
    if kf <= nf * p {
        return -log_nt;
    }
    // Natural log of the first term C(n, k) p^k (1-p)^(n-k).
    let log_first = log_gamma(nf + 1.0) - log_gamma(kf + 1.0) - log_gamma(nf - kf + 1.0)
        + kf * p.ln()
        + (nf - kf) * (1.0 - p).ln();
    let odds = p / (1.0 - p);
    let mut sum = 1.0f64;
    let mut term = 1.0f64;
    let mut j = k;
    while j < n && j - k < MAX_TAIL_TERMS {
        let ratio = (n - j) as f64 / (j + 1) as f64 * odds;
        term *= ratio;
        sum += term;
        j += 1;
        // Ratios decrease with j, so the remaining tail is bounded by a geometric series.
        let next = (n - j) as f64 / (j + 1) as f64 * odds;
        if next < 1.0 && term * next / (1.0 - next) <= sum * 1e-9 {
            break;
        }
    }
    let log10_tail = (log_first + sum.ln()) / LN_10;
    -log_nt - log10_tail
}

/// Gradient field of the working image.
struct Gradient {
    w: usize,
    h: usize,
    /// Level-line angle, `None` where the gradient is below threshold.
    angle: Vec<Option<f64>>,
    mag: Vec<f64>,
}

impl Gradient {
    fn new(img: &[f64], w: usize, h: usize, threshold: f64) -> Self {
        let mut angle = vec![None; w * h];
        let mut mag = vec![0.0; w * h];
        let at = |x: usize, y: usize| img.get(y * w + x).copied().unwrap_or(0.0);
        for y in 0..h.saturating_sub(1) {
            for x in 0..w.saturating_sub(1) {
                let (a, b) = (at(x, y), at(x + 1, y));
                let (c, d) = (at(x, y + 1), at(x + 1, y + 1));
                let gx = 0.5 * (b + d - a - c);
                let gy = 0.5 * (c + d - a - b);
                let m = (gx * gx + gy * gy).sqrt();
                let i = y * w + x;
                if let Some(v) = mag.get_mut(i) {
                    *v = m;
                }
                if m > threshold {
                    let ang = gx.atan2(-gy);
                    if ang.is_finite()
                        && let Some(v) = angle.get_mut(i)
                    {
                        *v = Some(ang);
                    }
                }
            }
        }
        Self { w, h, angle, mag }
    }

    fn angle(&self, x: usize, y: usize) -> Option<f64> {
        self.angle.get(y * self.w + x).copied().flatten()
    }

    fn mag(&self, x: usize, y: usize) -> f64 {
        self.mag.get(y * self.w + x).copied().unwrap_or(0.0)
    }
}

/// Pixels with a defined angle, by decreasing gradient-magnitude bin
/// (raster order inside a bin).
fn pseudo_order(g: &Gradient, bins: usize) -> Vec<usize> {
    let max = g
        .angle
        .iter()
        .zip(&g.mag)
        .filter(|(a, _)| a.is_some())
        .map(|(_, m)| *m)
        .fold(0.0f64, f64::max);
    if max <= 0.0 {
        return Vec::new();
    }
    let bin_of = |m: f64| ((m * bins as f64 / max) as usize).min(bins - 1);
    let mut counts = vec![0usize; bins];
    for (a, m) in g.angle.iter().zip(&g.mag) {
        if a.is_some()
            && let Some(c) = counts.get_mut(bin_of(*m))
        {
            *c += 1;
        }
    }
    // Start offsets with the highest bin first.
    let mut start = vec![0usize; bins];
    let mut acc = 0;
    for b in (0..bins).rev() {
        start[b] = acc;
        acc += counts[b];
    }
    let mut order = vec![0usize; acc];
    for (i, (a, m)) in g.angle.iter().zip(&g.mag).enumerate() {
        if a.is_some() {
            let b = bin_of(*m);
            if let Some(s) = start.get_mut(b) {
                if let Some(o) = order.get_mut(*s) {
                    *o = i;
                }
                *s += 1;
            }
        }
    }
    order
}

/// Signed difference `a − b` wrapped to `(−π, π]`.
fn angle_diff_signed(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(2.0 * PI);
    if d > PI { d - 2.0 * PI } else { d }
}

/// Whether a pixel angle is within `prec` of `theta` (undefined angles never are).
fn is_aligned(angle: Option<f64>, theta: f64, prec: f64) -> bool {
    angle.is_some_and(|a| angle_diff_signed(a, theta).abs() <= prec)
}

/// Grows a region from `seed` over unused pixels aligned (within `prec`) with
/// the running region angle; returns the final region angle.
fn region_grow(
    seed: (usize, usize),
    g: &Gradient,
    used: &mut [bool],
    prec: f64,
    reg: &mut Vec<(usize, usize)>,
) -> f64 {
    reg.clear();
    let Some(a0) = g.angle(seed.0, seed.1) else {
        return 0.0;
    };
    reg.push(seed);
    if let Some(u) = used.get_mut(seed.1 * g.w + seed.0) {
        *u = true;
    }
    let (mut sx, mut sy) = (a0.cos(), a0.sin());
    let mut theta = a0;
    let mut i = 0;
    while let Some(&(px, py)) = reg.get(i) {
        for ny in py.saturating_sub(1)..=(py + 1).min(g.h - 1) {
            for nx in px.saturating_sub(1)..=(px + 1).min(g.w - 1) {
                let idx = ny * g.w + nx;
                if used.get(idx).copied().unwrap_or(true) {
                    continue;
                }
                let a = g.angle(nx, ny);
                if is_aligned(a, theta, prec)
                    && let Some(a) = a
                {
                    if let Some(u) = used.get_mut(idx) {
                        *u = true;
                    }
                    reg.push((nx, ny));
                    sx += a.cos();
                    sy += a.sin();
                    theta = sy.atan2(sx);
                }
            }
        }
        i += 1;
    }
    theta
}

/// Oriented rectangle in working-image coordinates.
#[derive(Debug, Clone, Copy)]
struct Rect {
    x1: f64,
    y1: f64,
    x2: f64,
    y2: f64,
    width: f64,
    /// Centre.
    x: f64,
    y: f64,
    theta: f64,
    dx: f64,
    dy: f64,
    prec: f64,
    p: f64,
}

impl Rect {
    fn length(&self) -> f64 {
        (self.x2 - self.x1).hypot(self.y2 - self.y1)
    }

    /// Calls `f` for every in-image pixel whose centre lies in the rectangle.
    fn for_each_pixel(&self, w: usize, h: usize, mut f: impl FnMut(usize, usize)) {
        let (nx, ny) = (-self.dy * self.width * 0.5, self.dx * self.width * 0.5);
        let c = [
            (self.x1 + nx, self.y1 + ny),
            (self.x2 + nx, self.y2 + ny),
            (self.x2 - nx, self.y2 - ny),
            (self.x1 - nx, self.y1 - ny),
        ];
        if c.iter().any(|(x, y)| !x.is_finite() || !y.is_finite()) {
            return;
        }
        let ymin = c.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
        let ymax = c.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max);
        let y0 = ymin.ceil().max(0.0);
        let y1 = ymax.floor().min(h as f64 - 1.0);
        if y0 > y1 {
            return;
        }
        for yi in (y0 as usize)..=(y1 as usize) {
            let yf = yi as f64;
            let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
            for e in 0..4 {
                let (ax, ay) = c[e];
                let (bx, by) = c[(e + 1) % 4];
                if (ay - yf) * (by - yf) > 0.0 {
                    continue; // edge entirely above or below
                }
                if ay == by {
                    lo = lo.min(ax.min(bx));
                    hi = hi.max(ax.max(bx));
                } else {
                    let x = ax + (yf - ay) * (bx - ax) / (by - ay);
                    lo = lo.min(x);
                    hi = hi.max(x);
                }
            }
            let x0 = lo.ceil().max(0.0);
            let x1 = hi.floor().min(w as f64 - 1.0);
            if x0 > x1 {
                continue;
            }
            for xi in (x0 as usize)..=(x1 as usize) {
                f(xi, yi);
            }
        }
    }
}

/// Rectangle approximating a region: magnitude-weighted centre of mass,
/// principal inertia axis oriented like `reg_angle`, extent from the
/// projections of the region pixels.
fn region2rect(reg: &[(usize, usize)], g: &Gradient, reg_angle: f64, prec: f64, p: f64) -> Rect {
    let weights: Vec<f64> = reg.iter().map(|&(x, y)| g.mag(x, y)).collect();
    let mut sum: f64 = weights.iter().sum();
    let uniform = sum.is_nan() || sum <= 0.0;
    if uniform {
        sum = reg.len().max(1) as f64;
    }
    let wgt = |i: usize| {
        if uniform {
            1.0
        } else {
            weights.get(i).copied().unwrap_or(0.0)
        }
    };
    let (mut cx, mut cy) = (0.0, 0.0);
    for (i, &(x, y)) in reg.iter().enumerate() {
        cx += wgt(i) * x as f64;
        cy += wgt(i) * y as f64;
    }
    cx /= sum;
    cy /= sum;
    let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
    for (i, &(x, y)) in reg.iter().enumerate() {
        let (ex, ey) = (x as f64 - cx, y as f64 - cy);
        sxx += wgt(i) * ex * ex;
        syy += wgt(i) * ey * ey;
        sxy += wgt(i) * ex * ey;
    }
    let mut theta = if sxx == 0.0 && syy == 0.0 && sxy == 0.0 {
        reg_angle
    } else {
        0.5 * (2.0 * sxy).atan2(sxx - syy)
    };
    if angle_diff_signed(theta, reg_angle).abs() > prec {
        theta += PI;
    }
    let (dx, dy) = (theta.cos(), theta.sin());
    let (mut lmin, mut lmax, mut wmin, mut wmax) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for &(x, y) in reg {
        let (ex, ey) = (x as f64 - cx, y as f64 - cy);
        let l = ex * dx + ey * dy;
        let w = -ex * dy + ey * dx;
        lmin = lmin.min(l);
        lmax = lmax.max(l);
        wmin = wmin.min(w);
        wmax = wmax.max(w);
    }
    // Centre the rectangle on the band [wmin, wmax] across the axis.
    let wmid = 0.5 * (wmin + wmax);
    let (ox, oy) = (cx - dy * wmid, cy + dx * wmid);
    Rect {
        x1: ox + lmin * dx,
        y1: oy + lmin * dy,
        x2: ox + lmax * dx,
        y2: oy + lmax * dy,
        width: (wmax - wmin).max(1.0),
        x: ox + 0.5 * (lmin + lmax) * dx,
        y: oy + 0.5 * (lmin + lmax) * dy,
        theta,
        dx,
        dy,
        prec,
        p,
    }
}

/// Shared state of the refinement and validation steps.
struct Ctx<'a> {
    g: &'a Gradient,
    log_nt: f64,
    log_eps: f64,
    density_th: f64,
}

impl Ctx<'_> {
    fn density(reg_len: usize, r: &Rect) -> f64 {
        let area = r.length() * r.width;
        if area > 0.0 {
            reg_len as f64 / area
        } else {
            f64::INFINITY
        }
    }

    /// `−log10(NFA)` of a rectangle.
    fn rect_nfa(&self, r: &Rect) -> f64 {
        let (mut n, mut k) = (0u64, 0u64);
        r.for_each_pixel(self.g.w, self.g.h, |x, y| {
            n += 1;
            if is_aligned(self.g.angle(x, y), r.theta, r.prec) {
                k += 1;
            }
        });
        nfa(n, k, r.p, self.log_nt)
    }

    /// Makes the region/rectangle pair dense enough; false when it fails.
    #[allow(clippy::too_many_arguments)]
    fn refine(
        &self,
        reg: &mut Vec<(usize, usize)>,
        rect: &mut Rect,
        used: &mut [bool],
        prec: f64,
        p: f64,
        seed: (usize, usize),
    ) -> bool {
        if Self::density(reg.len(), rect) >= self.density_th {
            return true;
        }
        // New tolerance from the angles of the pixels near the seed.
        let Some(seed_angle) = self.g.angle(seed.0, seed.1) else {
            return false;
        };
        let (sx, sy) = (seed.0 as f64, seed.1 as f64);
        let (mut sum, mut sum2, mut cnt) = (0.0, 0.0, 0usize);
        for &(x, y) in reg.iter() {
            if (x as f64 - sx).hypot(y as f64 - sy) < rect.width
                && let Some(a) = self.g.angle(x, y)
            {
                let d = angle_diff_signed(a, seed_angle);
                sum += d;
                sum2 += d * d;
                cnt += 1;
            }
        }
        let tau = if cnt > 0 {
            let mean = sum / cnt as f64;
            2.0 * (sum2 / cnt as f64 - mean * mean).max(0.0).sqrt()
        } else {
            0.0
        };
        for &(x, y) in reg.iter() {
            if let Some(u) = used.get_mut(y * self.g.w + x) {
                *u = false;
            }
        }
        let reg_angle2 = region_grow(seed, self.g, used, tau, reg);
        if reg.len() < 2 {
            return false;
        }
        *rect = region2rect(reg, self.g, reg_angle2, prec, p);
        if Self::density(reg.len(), rect) >= self.density_th {
            return true;
        }
        self.reduce_region_radius(reg, rect, used, reg_angle2, prec, p, seed)
    }

    /// Removes the region points farthest from the seed until dense enough.
    #[allow(clippy::too_many_arguments)]
    fn reduce_region_radius(
        &self,
        reg: &mut Vec<(usize, usize)>,
        rect: &mut Rect,
        used: &mut [bool],
        reg_angle: f64,
        prec: f64,
        p: f64,
        seed: (usize, usize),
    ) -> bool {
        let (sx, sy) = (seed.0 as f64, seed.1 as f64);
        let mut rad = (rect.x1 - sx)
            .hypot(rect.y1 - sy)
            .max((rect.x2 - sx).hypot(rect.y2 - sy));
        let mut density = Self::density(reg.len(), rect);
        while density < self.density_th {
            rad *= 0.75;
            let w = self.g.w;
            reg.retain(|&(x, y)| {
                let keep = (x as f64 - sx).hypot(y as f64 - sy) <= rad;
                if !keep && let Some(u) = used.get_mut(y * w + x) {
                    *u = false;
                }
                keep
            });
            if reg.len() < 2 {
                return false;
            }
            *rect = region2rect(reg, self.g, reg_angle, prec, p);
            density = Self::density(reg.len(), rect);
        }
        true
    }

    /// Rectangle improvement steps; returns the best `−log10(NFA)`.
    fn rect_improve(&self, rect: &mut Rect) -> f64 {
        const DELTA: f64 = 0.5;
        let mut best = self.rect_nfa(rect);
        if best > self.log_eps {
            return best;
        }
        let try_steps = |rect: &mut Rect, best: &mut f64, step: &dyn Fn(&mut Rect) -> bool| {
            let mut r = *rect;
            for _ in 0..5 {
                if !step(&mut r) {
                    break;
                }
                let v = self.rect_nfa(&r);
                if v > *best {
                    *best = v;
                    *rect = r;
                }
            }
        };
        let finer = |r: &mut Rect| {
            r.p *= 0.5;
            r.prec = r.p * PI;
            true
        };
        let thinner = |r: &mut Rect| {
            if r.width - DELTA < 0.5 {
                return false;
            }
            r.width -= DELTA;
            true
        };
        let shift = |sign: f64| {
            move |r: &mut Rect| {
                if r.width - DELTA < 0.5 {
                    return false;
                }
                let (ox, oy) = (-r.dy * DELTA * 0.5 * sign, r.dx * DELTA * 0.5 * sign);
                r.x1 += ox;
                r.y1 += oy;
                r.x2 += ox;
                r.y2 += oy;
                r.x += ox;
                r.y += oy;
                r.width -= DELTA;
                true
            }
        };
        try_steps(rect, &mut best, &finer);
        if best > self.log_eps {
            return best;
        }
        try_steps(rect, &mut best, &thinner);
        if best > self.log_eps {
            return best;
        }
        try_steps(rect, &mut best, &shift(1.0));
        if best > self.log_eps {
            return best;
        }
        try_steps(rect, &mut best, &shift(-1.0));
        if best > self.log_eps {
            return best;
        }
        try_steps(rect, &mut best, &finer);
        best
    }
}

/// Gaussian subsampling by `scale` (separable, symmetric border).
fn gaussian_subsample(
    img: &[f64],
    w: usize,
    h: usize,
    scale: f64,
    sigma_scale: f64,
) -> Result<(Vec<f64>, usize, usize), String> {
    let nwf = (w as f64 * scale).ceil();
    let nhf = (h as f64 * scale).ceil();
    if nwf.is_nan() || nhf.is_nan() || nwf * nhf > MAX_PIXELS {
        return Err(format!(
            "subsampled image too large ({nwf} x {nhf}); reduce scale"
        ));
    }
    let (nw, nh) = (nwf as usize, nhf as usize);
    let sigma = if scale < 1.0 {
        sigma_scale / scale
    } else {
        sigma_scale
    };
    // Support where the Gaussian falls below 1e-3 of its peak.
    let half = (sigma * (2.0 * 3.0 * LN_10).sqrt())
        .ceil()
        .clamp(1.0, 4096.0) as isize;
    let mut kernel = vec![0.0; (2 * half + 1) as usize];
    let fill_kernel = |kernel: &mut Vec<f64>, offset: f64| {
        let mut s = 0.0;
        for (j, k) in kernel.iter_mut().enumerate() {
            let d = j as f64 - half as f64 - offset;
            *k = (-d * d / (2.0 * sigma * sigma)).exp();
            s += *k;
        }
        if s > 0.0 {
            kernel.iter_mut().for_each(|k| *k /= s);
        }
    };
    let reflect = |i: isize, n: usize| -> usize {
        let n = n as isize;
        let m = i.rem_euclid(2 * n);
        (if m < n { m } else { 2 * n - 1 - m }) as usize
    };
    // Horizontal pass: nw x h.
    let mut tmp = vec![0.0; nw * h];
    for xo in 0..nw {
        let xc = xo as f64 / scale;
        let xi = (xc + 0.5).floor();
        fill_kernel(&mut kernel, xc - xi);
        let xi = xi as isize;
        for y in 0..h {
            let mut acc = 0.0;
            for (j, k) in kernel.iter().enumerate() {
                let sx = reflect(xi + j as isize - half, w);
                acc += k * img.get(y * w + sx).copied().unwrap_or(0.0);
            }
            if let Some(t) = tmp.get_mut(y * nw + xo) {
                *t = acc;
            }
        }
    }
    // Vertical pass: nw x nh.
    let mut out = vec![0.0; nw * nh];
    for yo in 0..nh {
        let yc = yo as f64 / scale;
        let yi = (yc + 0.5).floor();
        fill_kernel(&mut kernel, yc - yi);
        let yi = yi as isize;
        for x in 0..nw {
            let mut acc = 0.0;
            for (j, k) in kernel.iter().enumerate() {
                let sy = reflect(yi + j as isize - half, h);
                acc += k * tmp.get(sy * nw + x).copied().unwrap_or(0.0);
            }
            if let Some(o) = out.get_mut(yo * nw + x) {
                *o = acc;
            }
        }
    }
    Ok((out, nw, nh))
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> f64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// 320x240, value 200, with a 200x120 rectangle of value 50 at (60, 60).
    fn rect_image() -> (Vec<f64>, usize, usize) {
        let (w, h) = (320, 240);
        let img = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                if (60..260).contains(&x) && (60..180).contains(&y) {
                    50.0
                } else {
                    200.0
                }
            })
            .collect();
        (img, w, h)
    }

    fn rotate_cw(img: &[f64], w: usize, h: usize) -> Vec<f64> {
        let mut r = vec![0.0; w * h];
        for y in 0..h {
            for x in 0..w {
                r[x * h + (h - 1 - y)] = img[y * w + x];
            }
        }
        r
    }

    /// Undirected angle difference in degrees, in [0, 90].
    fn line_angle_diff(a: (f64, f64, f64, f64), b: (f64, f64, f64, f64)) -> f64 {
        let ta = (a.3 - a.1).atan2(a.2 - a.0);
        let tb = (b.3 - b.1).atan2(b.2 - b.0);
        let d = (ta - tb).rem_euclid(PI);
        d.min(PI - d).to_degrees()
    }

    /// Whether some segment matches the expected one (endpoints in either order).
    fn matched(segs: &[Segment], e: (f64, f64, f64, f64), tol: f64, ang: f64) -> bool {
        segs.iter().any(|s| {
            let d = |ax: f64, ay: f64, bx: f64, by: f64| (ax - bx).hypot(ay - by);
            let same = d(s.x1, s.y1, e.0, e.1) <= tol && d(s.x2, s.y2, e.2, e.3) <= tol;
            let swap = d(s.x1, s.y1, e.2, e.3) <= tol && d(s.x2, s.y2, e.0, e.1) <= tol;
            (same || swap) && line_angle_diff((s.x1, s.y1, s.x2, s.y2), e) <= ang
        })
    }

    #[test]
    fn log_gamma_known_values() {
        let rel = |a: f64, b: f64| ((a - b) / b).abs();
        assert!(rel(log_gamma(5.0), 24f64.ln()) < 1e-8, "{}", log_gamma(5.0));
        assert!(rel(log_gamma(0.5), PI.sqrt().ln()) < 1e-8);
        assert!(rel(log_gamma(1.5), (PI.sqrt() / 2.0).ln()) < 1e-8);
        assert!(rel(log_gamma(11.0), 3_628_800f64.ln()) < 1e-8);
        // Windschitl branch: ln 20! and ln 99!.
        let lf = |n: u32| (1..=n).map(|i| (i as f64).ln()).sum::<f64>();
        assert!(rel(log_gamma(21.0), lf(20)) < 1e-8);
        assert!(rel(log_gamma(100.0), lf(99)) < 1e-8);
        assert!(log_gamma(0.0).is_infinite() && log_gamma(f64::NAN).is_infinite());
    }

    #[test]
    fn nfa_is_consistent() {
        // All 10 points aligned with p = 1/8: B = p^10.
        let v = nfa(10, 10, 0.125, 0.0);
        assert!((v - 10.0 * 8f64.log10()).abs() < 1e-8, "{v}");
        // B(3, 2, 0.5) = 4/8.
        let v = nfa(3, 2, 0.5, 1.0);
        assert!((v - (-1.0 - 0.5f64.log10())).abs() < 1e-9, "{v}");
        assert_eq!(nfa(0, 0, 0.125, 2.0), -2.0);
    }

    #[test]
    fn rectangle_sides_are_detected() {
        let (img, w, h) = rect_image();
        let segs = detect_segments(&img, w, h, &LsdParams::default()).unwrap();
        let sides = [
            (59.5, 59.5, 259.5, 59.5),
            (259.5, 59.5, 259.5, 179.5),
            (259.5, 179.5, 59.5, 179.5),
            (59.5, 179.5, 59.5, 59.5),
        ];
        for s in sides {
            assert!(
                matched(&segs, s, 2.0, 1.0),
                "side {s:?} not found in {segs:#?}"
            );
        }
        for s in &segs {
            assert!(s.log_nfa > 0.0 && s.p > 0.0 && s.width > 0.0);
        }
    }

    #[test]
    fn noisy_rectangle_is_detected_deterministically() {
        let (mut img, w, h) = rect_image();
        let mut rng = Rng(42);
        for v in &mut img {
            *v += (rng.next() + rng.next() + rng.next() - 1.5) * 15.0;
        }
        let p = LsdParams::default();
        let segs = detect_segments(&img, w, h, &p).unwrap();
        let sides = [
            (59.5, 59.5, 259.5, 59.5),
            (259.5, 59.5, 259.5, 179.5),
            (259.5, 179.5, 59.5, 179.5),
            (59.5, 179.5, 59.5, 59.5),
        ];
        for s in sides {
            assert!(
                matched(&segs, s, 3.0, 1.0),
                "side {s:?} not found in {segs:#?}"
            );
        }
        assert!(segs.len() <= 6, "{segs:#?}");
        assert_eq!(segs, detect_segments(&img, w, h, &p).unwrap());
    }

    #[test]
    fn constant_and_noise_give_no_segments() {
        let p = LsdParams::default();
        let flat = vec![128.0; 100 * 80];
        assert!(detect_segments(&flat, 100, 80, &p).unwrap().is_empty());
        let mut rng = Rng(0x2545_F491_4F6C_DD1D);
        let noise: Vec<f64> = (0..200 * 200).map(|_| rng.next() * 255.0).collect();
        let segs = detect_segments(&noise, 200, 200, &p).unwrap();
        assert!(segs.len() <= 1, "{segs:#?}");
    }

    #[test]
    fn rotation_rotates_segments() {
        let (img, w, h) = rect_image();
        let p = LsdParams::default();
        let segs = detect_segments(&img, w, h, &p).unwrap();
        let rot = detect_segments(&rotate_cw(&img, w, h), h, w, &p).unwrap();
        assert_eq!(segs.len(), rot.len());
        // (x, y) -> (h - 1 - y, x).
        let hh = h as f64 - 1.0;
        for s in &segs {
            let e = (hh - s.y1, s.x1, hh - s.y2, s.x2);
            assert!(matched(&rot, e, 2.0, 1.0), "{s:?} not found rotated");
        }
    }

    #[test]
    fn draw_paints_segment_pixels() {
        let (w, h) = (20, 10);
        let gray = vec![100.0; w * h];
        let seg = Segment {
            x1: 2.0,
            y1: 3.0,
            x2: 15.0,
            y2: 3.0,
            width: 1.0,
            p: 0.125,
            log_nfa: 5.0,
        };
        let far = Segment {
            x1: -1e300,
            y1: 5.0,
            x2: f64::INFINITY,
            y2: 5.0,
            ..seg
        };
        let rgb = draw_segments(&gray, w, h, &[seg, far]);
        assert_eq!(rgb.len(), w * h * 3);
        for x in 2..=15 {
            let i = (3 * w + x) * 3;
            assert_eq!(&rgb[i..i + 3], &[255, 0, 0]);
        }
        let i = (7 * w + 5) * 3;
        assert_eq!(&rgb[i..i + 3], &[100, 100, 100]);
        let long = Segment {
            x1: -1e12,
            y1: 8.0,
            x2: 1e12,
            y2: 8.0,
            ..seg
        };
        let rgb = draw_segments(&gray, w, h, &[long]);
        let i = (8 * w + 10) * 3;
        assert_eq!(&rgb[i..i + 3], &[255, 0, 0]);
    }

    #[test]
    fn invalid_inputs() {
        let ok = LsdParams::default();
        let img = vec![0.0; 12];
        assert!(detect_segments(&[], 0, 0, &ok).unwrap().is_empty());
        assert!(detect_segments(&[], 0, 7, &ok).unwrap().is_empty());
        assert!(detect_segments(&img, 4, 3, &ok).unwrap().is_empty());
        assert!(detect_segments(&[1.0], 1, 1, &ok).unwrap().is_empty());
        assert!(detect_segments(&img, 5, 3, &ok).is_err());
        assert!(detect_segments(&img, usize::MAX, 3, &ok).is_err());
        let mut nan = img.clone();
        nan[3] = f64::NAN;
        assert!(detect_segments(&nan, 4, 3, &ok).is_err());
        for bad in [
            LsdParams { scale: 0.0, ..ok },
            LsdParams { scale: -1.0, ..ok },
            LsdParams {
                scale: f64::NAN,
                ..ok
            },
            LsdParams {
                scale: f64::INFINITY,
                ..ok
            },
            LsdParams { scale: 1e9, ..ok },
            LsdParams {
                sigma_scale: 0.0,
                ..ok
            },
            LsdParams {
                angle_tolerance_deg: 0.0,
                ..ok
            },
            LsdParams {
                density_threshold: 1.5,
                ..ok
            },
            LsdParams { bins: 0, ..ok },
            LsdParams {
                log_eps: f64::NAN,
                ..ok
            },
        ] {
            assert!(detect_segments(&img, 4, 3, &bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    #[ignore = "timing, run with --release -- --ignored"]
    fn timing_640x480() {
        let (w, h) = (640, 480);
        let mut rng = Rng(99);
        let img: Vec<f64> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                let mut v = 60.0;
                if (x - 320.0).hypot(y - 240.0) < 150.0 {
                    v = 180.0;
                }
                if (100.0..540.0).contains(&x) && (50.0..120.0).contains(&y) {
                    v = 120.0;
                }
                if x + 2.0 * y > 900.0 && x + 2.0 * y < 940.0 {
                    v = 230.0;
                }
                v + rng.next() * 20.0
            })
            .collect();
        let t0 = std::time::Instant::now();
        let segs = detect_segments(&img, w, h, &LsdParams::default()).unwrap();
        println!(
            "detect_segments 640x480 (defaults): {:?}, {} segments",
            t0.elapsed(),
            segs.len()
        );
        assert!(!segs.is_empty());
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn never_panics(
            w in 0usize..24,
            h in 0usize..24,
            seed in any::<u64>(),
            scale in 0.2f64..2.0,
            tol in 1.0f64..90.0,
            bins in 1usize..2000,
        ) {
            let mut rng = Rng(seed | 1);
            let img: Vec<f64> = (0..w * h)
                .map(|i| if rng.next() < 0.5 { 255.0 * rng.next() } else { 40.0 * ((i % w.max(1)) as f64 > w as f64 / 2.0) as u8 as f64 })
                .collect();
            let p = LsdParams { scale, angle_tolerance_deg: tol, bins, ..LsdParams::default() };
            let segs = detect_segments(&img, w, h, &p).unwrap();
            for s in &segs {
                prop_assert!(s.x1.is_finite() && s.y2.is_finite() && s.log_nfa > 0.0);
            }
            let rgb = draw_segments(&img, w, h, &segs);
            prop_assert_eq!(rgb.len(), w * h * 3);
        }
    }
}
