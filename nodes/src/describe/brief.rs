//! `describe.brief`: BRIEF binary descriptors (Calonder et al., ECCV 2010) at given keypoints.
//!
//! [`brief_describe`] smooths the gray image with a Gaussian, then, for every keypoint whose
//! test pattern fits inside the image, compares `8 · bytes` pairs of smoothed samples around the
//! keypoint (rounded to the nearest pixel): bit `j` of byte `i` is 1 when the first sample of test
//! `8i + j` is darker than the second. The test pattern is one of the paper's five sampling
//! strategies (G I – G V), drawn once from a fixed-seed generator ([`SplitMix64`]), so the same
//! parameters always give the same pattern.
//!
//! Keypoints are described independently in parallel and collected in input order, so the output
//! does not depend on the thread count.
//!
//! The sampling helpers here ([`SplitMix64`], [`gaussian_pair`]) are shared with `describe.orb`.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Descriptors, Image, Keypoint, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use crate::detect::gray::gray_u8;
use crate::filter::border::BorderMode;
use crate::filter::gaussian::gaussian_blur;

/// Seed of the BRIEF test patterns.
const BRIEF_SEED: u64 = 0x0B41_EF00_2010_0001;

/// Largest patch side, pixels.
const MAX_PATCH: u32 = 255;

/// Keypoints per parallel work item.
const CHUNK: usize = 64;

/// The splitmix64 generator (Steele, Lea, Flood 2014): a tiny deterministic source of the
/// pseudo-random test patterns.
#[derive(Debug, Clone)]
pub(crate) struct SplitMix64(u64);

impl SplitMix64 {
    pub(crate) fn new(seed: u64) -> SplitMix64 {
        SplitMix64(seed)
    }

    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub(crate) fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform integer in `0..n` (`n > 0`).
    pub(crate) fn below(&mut self, n: usize) -> usize {
        ((self.uniform() * n as f64) as usize).min(n.saturating_sub(1))
    }

    /// Standard normal (Box–Muller, the cosine branch).
    pub(crate) fn normal(&mut self) -> f64 {
        let u1 = 1.0 - self.uniform(); // (0, 1]
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

/// One point drawn from an isotropic Gaussian of standard deviation `sigma` centred at
/// `(cx, cy)`, rounded to the nearest pixel; redrawn until `inside` accepts it.
pub(crate) fn gaussian_point(
    rng: &mut SplitMix64,
    cx: f64,
    cy: f64,
    sigma: f64,
    inside: impl Fn(i32, i32) -> bool,
) -> (i32, i32) {
    loop {
        let x = (cx + sigma * rng.normal()).round() as i32;
        let y = (cy + sigma * rng.normal()).round() as i32;
        if inside(x, y) {
            return (x, y);
        }
    }
}

/// A test of two distinct points, each from an isotropic Gaussian around the centre (BRIEF's
/// G II), redrawn until `inside` accepts both.
pub(crate) fn gaussian_pair(
    rng: &mut SplitMix64,
    sigma: f64,
    inside: impl Fn(i32, i32) -> bool + Copy,
) -> [i32; 4] {
    loop {
        let (x1, y1) = gaussian_point(rng, 0.0, 0.0, sigma, inside);
        let (x2, y2) = gaussian_point(rng, 0.0, 0.0, sigma, inside);
        if (x1, y1) != (x2, y2) {
            return [x1, y1, x2, y2];
        }
    }
}

param_enum! {
    /// BRIEF test sampling strategy (Calonder et al. 2010, section 3.2, Fig. 2). `S` is the patch
    /// side; coordinates are integers in `[−r, r]`, `r = ⌊(S − 1)/2⌋`.
    pub enum BriefPattern {
        /// G I: both points uniform over the patch.
        Uniform = "uniform",
        /// G II: both points from an isotropic Gaussian, σ = S/5 (the paper's recommendation).
        Gaussian = "gaussian",
        /// G III: first point Gaussian (σ = S/5), second Gaussian around the first (σ = S/10).
        GaussianPair = "gaussian_pair",
        /// G IV: both points drawn from the vertices of a coarse polar grid.
        Polar = "polar",
        /// G V: first point the centre, second every vertex of the coarse polar grid in turn.
        PolarCentered = "polar_centered",
    }
}

#[allow(clippy::derivable_impls)]
impl Default for BriefPattern {
    fn default() -> Self {
        BriefPattern::Gaussian
    }
}

/// Vertices of the coarse polar grid with `n` vertices (16 angles per ring, `n / 16` rings at
/// radii `r · (k + 1) / rings`, odd rings rotated by half a step), rounded to pixels. Inner rings
/// round some vertices onto the same pixel; they are kept (the grid is coarse by design).
fn polar_grid(n: usize, r: i32) -> Vec<(i32, i32)> {
    let rings = n.div_ceil(16).max(1);
    let mut grid = Vec::with_capacity(n);
    for k in 0..rings {
        let radius = f64::from(r) * (k + 1) as f64 / rings as f64;
        for j in 0..16 {
            if grid.len() == n {
                break;
            }
            let shift = if k % 2 == 1 { 0.5 } else { 0.0 };
            let theta = std::f64::consts::TAU * (j as f64 + shift) / 16.0;
            grid.push((
                (radius * theta.cos()).round() as i32,
                (radius * theta.sin()).round() as i32,
            ));
        }
    }
    grid
}

/// The `tests` point pairs `[x1, y1, x2, y2]` of `pattern` for a patch of side `patch`.
pub fn brief_pattern(pattern: BriefPattern, tests: usize, patch: usize) -> Vec<[i32; 4]> {
    let r = ((patch.max(1) - 1) / 2) as i32;
    let s = patch as f64;
    let mut rng = SplitMix64::new(BRIEF_SEED ^ ((patch as u64) << 16) ^ pattern as u64);
    let inside = move |x: i32, y: i32| x.abs() <= r && y.abs() <= r;
    let mut out = Vec::with_capacity(tests);
    if r == 0 {
        return vec![[0; 4]; tests];
    }
    match pattern {
        BriefPattern::Uniform => {
            let side = (2 * r + 1) as usize;
            while out.len() < tests {
                let p = [
                    rng.below(side) as i32 - r,
                    rng.below(side) as i32 - r,
                    rng.below(side) as i32 - r,
                    rng.below(side) as i32 - r,
                ];
                if (p[0], p[1]) != (p[2], p[3]) {
                    out.push(p);
                }
            }
        }
        BriefPattern::Gaussian => {
            while out.len() < tests {
                out.push(gaussian_pair(&mut rng, s / 5.0, inside));
            }
        }
        BriefPattern::GaussianPair => {
            while out.len() < tests {
                let (x1, y1) = gaussian_point(&mut rng, 0.0, 0.0, s / 5.0, inside);
                let (x2, y2) =
                    gaussian_point(&mut rng, f64::from(x1), f64::from(y1), s / 10.0, inside);
                if (x1, y1) != (x2, y2) {
                    out.push([x1, y1, x2, y2]);
                }
            }
        }
        BriefPattern::Polar => {
            let grid = polar_grid(tests, r);
            while out.len() < tests {
                let a = grid[rng.below(grid.len())];
                let b = grid[rng.below(grid.len())];
                if a != b {
                    out.push([a.0, a.1, b.0, b.1]);
                }
            }
        }
        BriefPattern::PolarCentered => {
            out.extend(polar_grid(tests, r).iter().map(|&(x, y)| [0, 0, x, y]));
        }
    }
    out
}

params! {
    /// Parameters of `describe.brief`.
    pub struct BriefParams {
        /// Descriptor length in bytes: 16, 32 or 64 (128, 256 or 512 tests; default 32).
        bytes: u32 = 32,
        /// Test sampling strategy (default "gaussian", the paper's G II).
        pattern: BriefPattern = BriefPattern::Gaussian,
        /// Patch side S in pixels (3..=255, default 48 as in the paper): tests lie within
        /// ±⌊(S − 1)/2⌋ px of the keypoint.
        patch_size: u32 = 48,
        /// Standard deviation of the Gaussian pre-smoothing, pixels (default 2.0, the paper's);
        /// 0 disables smoothing.
        smoothing_sigma: f64 = 2.0,
        /// Side of the smoothing kernel, pixels (odd, default 9 as in the paper; 0 derives it
        /// from the sigma).
        smoothing_ksize: u32 = 9,
    }
}

fn validate(p: &BriefParams) -> Result<(), String> {
    if ![16, 32, 64].contains(&p.bytes) {
        return Err(format!("`bytes` must be 16, 32 or 64, got {}", p.bytes));
    }
    if !(3..=MAX_PATCH).contains(&p.patch_size) {
        return Err(format!(
            "`patch_size` must be between 3 and {MAX_PATCH}, got {}",
            p.patch_size
        ));
    }
    if !p.smoothing_sigma.is_finite() || !(0.0..=100.0).contains(&p.smoothing_sigma) {
        return Err(format!(
            "`smoothing_sigma` must be a finite number in [0, 100], got {}",
            p.smoothing_sigma
        ));
    }
    if p.smoothing_ksize != 0 && (p.smoothing_ksize.is_multiple_of(2) || p.smoothing_ksize > 255) {
        return Err(format!(
            "`smoothing_ksize` must be 0 or odd up to 255, got {}",
            p.smoothing_ksize
        ));
    }
    Ok(())
}

/// Gaussian-smoothed gray u8 copy of `gray` (`sigma` 0: unchanged), border reflect101.
pub(crate) fn smooth_gray(
    gray: &[u8],
    width: usize,
    height: usize,
    sigma: f64,
    ksize: usize,
) -> Result<Vec<u8>, String> {
    if sigma <= 0.0 || gray.is_empty() {
        return Ok(gray.to_vec());
    }
    let image =
        Image::from_u8(width, height, Channels::Gray, gray.to_vec()).map_err(|e| e.to_string())?;
    let blurred = gaussian_blur(
        &image,
        sigma,
        sigma,
        ksize,
        ksize,
        BorderMode::Reflect101,
        0.0,
    );
    blurred
        .as_u8()
        .map(<[u8]>::to_vec)
        .ok_or_else(|| "internal: smoothing changed the sample type".to_string())
}

/// Packs the outcomes of `tests.len()` comparisons at `(cx, cy)` into `out` (bit `j` of byte
/// `i` = test `8i + j`, 1 when the first sample is darker). All points must lie inside.
fn describe_at(img: &[u8], width: usize, cx: usize, cy: usize, tests: &[[i32; 4]], out: &mut [u8]) {
    let centre = (cy * width + cx) as isize;
    let w = width as isize;
    for (byte, group) in out.iter_mut().zip(tests.chunks(8)) {
        let mut v = 0u8;
        for (j, t) in group.iter().enumerate() {
            let a = img[(centre + t[1] as isize * w + t[0] as isize) as usize];
            let b = img[(centre + t[3] as isize * w + t[2] as isize) as usize];
            v |= u8::from(a < b) << j;
        }
        *byte = v;
    }
}

/// BRIEF descriptors of `keypoints` on `image` (any format; converted to gray u8 as
/// `detect.gray` does). Returns the keypoints kept (those whose rounded centre is at least
/// `r = ⌊(patch_size − 1)/2⌋` px from every border; NaN coordinates are dropped) and their
/// descriptors, in input order.
pub fn brief_describe(
    image: &Image,
    keypoints: &[Keypoint],
    params: &BriefParams,
) -> Result<(Vec<Keypoint>, Descriptors), String> {
    validate(params)?;
    let bytes = params.bytes as usize;
    let patch = params.patch_size as usize;
    let r = ((patch - 1) / 2) as f32;
    let (w, h) = (image.width(), image.height());
    let kept: Vec<(Keypoint, usize, usize)> = keypoints
        .iter()
        .filter_map(|k| {
            let (x, y) = (k.x.round_ties_even(), k.y.round_ties_even());
            if x.is_finite()
                && y.is_finite()
                && x >= r
                && y >= r
                && x + r < w as f32
                && y + r < h as f32
            {
                Some((*k, x as usize, y as usize))
            } else {
                None
            }
        })
        .collect();
    let mut data = vec![0u8; kept.len() * bytes];
    if !kept.is_empty() {
        let gray = gray_u8(image);
        let smooth = smooth_gray(
            &gray,
            w,
            h,
            params.smoothing_sigma,
            params.smoothing_ksize as usize,
        )?;
        let tests = brief_pattern(params.pattern, bytes * 8, patch);
        data.par_chunks_mut(bytes * CHUNK)
            .zip(kept.par_chunks(CHUNK))
            .for_each(|(rows, kps)| {
                for (row, &(_, x, y)) in rows.chunks_mut(bytes).zip(kps) {
                    describe_at(&smooth, w, x, y, &tests, row);
                }
            });
    }
    Ok((
        kept.into_iter().map(|(k, _, _)| k).collect(),
        Descriptors::Binary { bytes, data },
    ))
}

/// BRIEF descriptor extractor (`describe.brief`). See [`brief_describe`].
#[derive(Debug, Clone)]
pub struct Brief(BriefParams);

impl Op for Brief {
    type Params = BriefParams;
    const ID: &'static str = "describe.brief";
    const SUMMARY: &'static str =
        "BRIEF binary descriptors (smoothed pixel-pair tests) at given keypoints.";
    const DOC: &'static str = r#"
Binary Robust Independent Elementary Features: the image (converted to gray u8: u16 as
round(v/257), f32 as round(clamp(v, 0, 1)·255), colour as BT.601 luma) is smoothed with a
Gaussian (`smoothing_sigma`, `smoothing_ksize`; the paper's 9×9, σ = 2), then each keypoint gets
8·`bytes` binary tests τ(p; x, y) = 1 if p(x) < p(y), at integer offsets around its centre
rounded to the nearest pixel. Bit j of byte i is test 8i + j.

Test patterns (`pattern`, the paper's Fig. 2), patch side S, offsets within ±⌊(S−1)/2⌋:
- "uniform" (G I): both points i.i.d. uniform over the patch;
- "gaussian" (G II, default): both i.i.d. isotropic Gaussian, σ = S/5;
- "gaussian_pair" (G III): x Gaussian σ = S/5, y Gaussian around x with σ = S/10;
- "polar" (G IV): both points random vertices of a coarse polar grid;
- "polar_centered" (G V): x the centre, y every vertex of the polar grid (16 angles per ring,
  8·bytes/16 rings evenly spaced in radius).
Gaussian samples outside the patch are redrawn. Patterns come from a fixed-seed splitmix64
generator: deterministic, but not OpenCV's tables (`cv::xfeatures2d::BriefDescriptorExtractor`
uses its own G II pattern and a box filter on an integral image instead of the Gaussian).

Keypoints whose rounded centre is closer than ⌊(S−1)/2⌋ px to a border are dropped; the
`keypoints` output holds those kept, in input order, one descriptor row each. Angle and size
are ignored (BRIEF is neither rotation- nor scale-invariant; use describe.orb for that).

Reference: M. Calonder, V. Lepetit, C. Strecha, P. Fua, "BRIEF: Binary Robust Independent
Elementary Features", ECCV 2010.

Example:
    "brief": (op: "describe.brief", inputs: { "image": "gray.image", "keypoints": "fast.keypoints" }, params: (bytes: 32, pattern: "gaussian")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("image", PortType::Image, "Image to describe (any format)."),
            PortSpec::new(
                "keypoints",
                PortType::Keypoints,
                "Where to compute descriptors.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "keypoints",
                PortType::Keypoints,
                "The keypoints kept (patch inside the image), input order.",
            ),
            PortSpec::new(
                "descriptors",
                PortType::Descriptors,
                "Binary descriptors, one row of `bytes` bytes per kept keypoint.",
            ),
        ]
    }

    fn new(params: BriefParams) -> Result<Self, String> {
        validate(&params)?;
        Ok(Brief(params))
    }
}

impl Operator for Brief {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let keypoints = match inputs.require("keypoints")? {
            Value::Keypoints(k) => k.clone(),
            other => {
                return Err(OpError::input(
                    "keypoints",
                    format!("expected keypoints, got {:?}", other.port_type()),
                ));
            }
        };
        let (kept, descriptors) =
            brief_describe(image, &keypoints, &self.0).map_err(|e| OpError::input("image", e))?;
        Ok(Outputs::new()
            .with("keypoints", Value::Keypoints(kept.into()))
            .with("descriptors", Value::Descriptors(descriptors.into())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kp(x: f32, y: f32) -> Keypoint {
        Keypoint {
            x,
            y,
            size: 7.0,
            angle: -1.0,
            response: 0.0,
            octave: 0,
        }
    }

    fn no_smoothing(pattern: BriefPattern, bytes: u32, patch: u32) -> BriefParams {
        BriefParams {
            bytes,
            pattern,
            patch_size: patch,
            smoothing_sigma: 0.0,
            smoothing_ksize: 0,
        }
    }

    fn bits(desc: &[u8]) -> Vec<bool> {
        desc.iter()
            .flat_map(|&b| (0..8).map(move |j| b >> j & 1 == 1))
            .collect()
    }

    #[test]
    fn hand_computed_bits_on_a_tiny_image() {
        // 5×5 image, patch 5 (offsets within ±2): value = 10·x + y, so a test is 1 exactly
        // when its first point is left of the second, or in the same column and above it.
        let (w, h) = (5usize, 5usize);
        let data: Vec<u8> = (0..w * h).map(|i| (10 * (i % w) + i / w) as u8).collect();
        let image = Image::from_u8(w, h, Channels::Gray, data).unwrap();
        for pattern in [
            BriefPattern::Uniform,
            BriefPattern::Gaussian,
            BriefPattern::GaussianPair,
            BriefPattern::Polar,
            BriefPattern::PolarCentered,
        ] {
            let p = no_smoothing(pattern, 16, 5);
            let (kept, d) = brief_describe(&image, &[kp(2.0, 2.0), kp(1.0, 2.0)], &p).unwrap();
            assert_eq!(kept.len(), 1, "only the centre fits the patch");
            let Descriptors::Binary { bytes, data } = d else {
                panic!("binary expected")
            };
            assert_eq!((bytes, data.len()), (16, 16));
            let tests = brief_pattern(pattern, 128, 5);
            let expected: Vec<bool> = tests
                .iter()
                .map(|t| t[0] < t[2] || (t[0] == t[2] && t[1] < t[3]))
                .collect();
            assert_eq!(bits(&data), expected, "{pattern:?}");
        }
        // A fully hand-checked case: G V's outer ring (the 8th, radius 2, tests 112..128) starts
        // at 11.25°, i.e. the test (0,0) vs (round(1.96), round(0.39)) = (2,0): 22 < 42 → 1; its
        // vertex at 191.25° is (−2, 0): 22 < 2 is false.
        let tests = brief_pattern(BriefPattern::PolarCentered, 128, 5);
        assert_eq!(tests[112], [0, 0, 2, 0]);
        assert_eq!(tests[120], [0, 0, -2, 0]);
        let (_, d) = brief_describe(
            &image,
            &[kp(2.0, 2.0)],
            &no_smoothing(BriefPattern::PolarCentered, 16, 5),
        )
        .unwrap();
        let Descriptors::Binary { data, .. } = d else {
            panic!()
        };
        assert_eq!(data[14] & 1, 1);
        assert_eq!(data[15] & 1, 0);
    }

    #[test]
    fn patterns_stay_inside_and_follow_their_distribution() {
        for pattern in [
            BriefPattern::Uniform,
            BriefPattern::Gaussian,
            BriefPattern::GaussianPair,
            BriefPattern::Polar,
            BriefPattern::PolarCentered,
        ] {
            for tests in [128, 256, 512] {
                let p = brief_pattern(pattern, tests, 48);
                assert_eq!(p.len(), tests);
                assert!(p.iter().flatten().all(|&c| c.abs() <= 23));
                assert_eq!(p, brief_pattern(pattern, tests, 48), "deterministic");
            }
        }
        // G II: spread ≈ S/5 = 9.6 per coordinate (truncation at ±23 shrinks it a little);
        // G III: the second point within ≈ S/10 of the first.
        let g = brief_pattern(BriefPattern::Gaussian, 512, 48);
        let var = g.iter().map(|t| f64::from(t[0] * t[0])).sum::<f64>() / 512.0;
        assert!((7.5..11.0).contains(&var.sqrt()), "{}", var.sqrt());
        let g3 = brief_pattern(BriefPattern::GaussianPair, 512, 48);
        let d = g3
            .iter()
            .map(|t| f64::from((t[2] - t[0]).pow(2)))
            .sum::<f64>()
            / 512.0;
        assert!((3.5..6.0).contains(&d.sqrt()), "{}", d.sqrt());
        let u = brief_pattern(BriefPattern::Uniform, 512, 48);
        let var = u.iter().map(|t| f64::from(t[0] * t[0])).sum::<f64>() / 512.0;
        // Uniform on −23..=23: σ = sqrt((47² − 1)/12) ≈ 13.6.
        assert!((12.0..15.0).contains(&var.sqrt()), "{}", var.sqrt());
        assert!(
            brief_pattern(BriefPattern::PolarCentered, 256, 48)
                .iter()
                .all(|t| t[0] == 0 && t[1] == 0)
        );
    }

    #[test]
    fn smoothing_and_formats() {
        // A random texture: u8, u16 (×257) and f32 (/255) give the same bits.
        let (w, h) = (64, 64);
        let g = crate::filter::test_support::random_u8(w, h, Channels::Gray, 5);
        let v = g.as_u8().unwrap().to_vec();
        let g16 = Image::from_u16(
            w,
            h,
            Channels::Gray,
            v.iter().map(|&s| u16::from(s) * 257).collect(),
        )
        .unwrap();
        let gf = Image::from_f32(
            w,
            h,
            Channels::Gray,
            v.iter().map(|&s| f32::from(s) / 255.0).collect(),
        )
        .unwrap();
        let kps: Vec<Keypoint> = (0..10).map(|i| kp(24.0 + i as f32, 30.0)).collect();
        let p = BriefParams::default();
        let a = brief_describe(&g, &kps, &p).unwrap();
        assert_eq!(a.0.len(), 10);
        assert_eq!(brief_describe(&g16, &kps, &p).unwrap(), a);
        assert_eq!(brief_describe(&gf, &kps, &p).unwrap(), a);
        // Smoothing changes the bits of a noise image.
        let raw = brief_describe(&g, &kps, &no_smoothing(BriefPattern::Gaussian, 32, 48)).unwrap();
        assert_ne!(raw.1, a.1);
    }

    #[test]
    fn extremes_and_border() {
        let p = BriefParams::default();
        for (w, h) in [(0, 0), (1, 1), (8, 8), (47, 47)] {
            let img = Image::from_u8(w, h, Channels::Gray, vec![7; w * h]).unwrap();
            let (k, d) =
                brief_describe(&img, &[kp(0.0, 0.0), kp(4.0, 4.0), kp(f32::NAN, 3.0)], &p).unwrap();
            assert!(k.is_empty() && d.is_empty());
        }
        // 47×47 with patch 47 (r = 23): only the centre fits.
        let img = Image::from_u8(47, 47, Channels::Gray, vec![7; 47 * 47]).unwrap();
        let q = BriefParams {
            patch_size: 47,
            ..BriefParams::default()
        };
        let (k, d) =
            brief_describe(&img, &[kp(23.0, 23.0), kp(24.0, 23.0), kp(22.6, 23.4)], &q).unwrap();
        assert_eq!(k.len(), 2);
        // Constant image: every test is "not darker".
        let Descriptors::Binary { data, .. } = d else {
            panic!()
        };
        assert!(data.iter().all(|&b| b == 0));
    }

    #[test]
    fn deterministic_across_threads_and_rejects_bad_params() {
        let (w, h) = (200, 150);
        let g = crate::filter::test_support::random_u8(w, h, Channels::Gray, 8);
        let kps: Vec<Keypoint> = (0..500)
            .map(|i| kp(24.0 + (i * 7 % 150) as f32, 24.0 + (i * 13 % 100) as f32))
            .collect();
        let p = BriefParams::default();
        let many = brief_describe(&g, &kps, &p).unwrap();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        assert_eq!(pool.install(|| brief_describe(&g, &kps, &p)).unwrap(), many);
        for bad in [
            BriefParams {
                bytes: 20,
                ..p.clone()
            },
            BriefParams {
                patch_size: 2,
                ..p.clone()
            },
            BriefParams {
                smoothing_sigma: f64::NAN,
                ..p.clone()
            },
            BriefParams {
                smoothing_ksize: 4,
                ..p.clone()
            },
        ] {
            assert!(Brief::new(bad).is_err());
        }
    }
}
