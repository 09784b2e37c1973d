//! `filter.frequency_filter`: ideal, Gaussian and Butterworth low/high-pass filters applied in
//! the Fourier domain.
//!
//! Each channel goes through the real-input FFT of [`super::fft`] (half spectrum, transposed),
//! is multiplied by the transfer function `H(D)`, a function of the radial frequency only, and
//! comes back through the real-output inverse FFT. `H` is real and even, so the product stays
//! Hermitian and the result is real. The filtering is circular: the image is treated as one
//! period of a periodic signal (the spatial equivalent uses a `wrap` border).

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, Value, ValueError};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;
use rustfft::FftPlanner;

use super::fft::{real_from_spectrum_half, real_spectrum_half};
use super::{from_planes, to_planes};

/// Largest accepted cutoff, in cycles per pixel (the corner frequency is √2/2 ≈ 0.707).
pub const MAX_CUTOFF: f64 = 1.0;

/// Largest Butterworth order.
pub const MAX_ORDER: u32 = 32;

param_enum! {
    /// Shape of the transfer function.
    pub enum FilterKind {
        /// Ideal (brick wall): low-pass H = 1 for D ≤ D0, else 0. Rings.
        Ideal = "ideal",
        /// Gaussian: low-pass H = exp(−D²/(2·D0²)). No ringing.
        Gaussian = "gaussian",
        /// Butterworth: low-pass H = 1/(1 + (D/D0)^(2·order)).
        Butterworth = "butterworth",
    }
}

param_enum! {
    /// Which band is kept.
    pub enum PassBand {
        /// Keep frequencies below the cutoff.
        Low = "low",
        /// Keep frequencies above the cutoff: H_high = 1 − H_low.
        High = "high",
    }
}

params! {
    /// Parameters of `filter.frequency_filter`.
    pub struct FrequencyFilterParams {
        /// Transfer function shape: "ideal", "gaussian" or "butterworth".
        kind: FilterKind = FilterKind::Gaussian,
        /// "low" keeps low frequencies, "high" keeps high ones (1 − low).
        pass: PassBand = PassBand::Low,
        /// Cutoff D0 in cycles per pixel, radial: 0 < D0 ≤ 1 (Nyquist is 0.5 along an axis,
        /// √2/2 at the corners). For "gaussian" it is the standard deviation of H; a spatial
        /// Gaussian blur of σ px corresponds to D0 = 1/(2πσ).
        cutoff: f64 = 0.1 => [above = 0.0, max = 1.0, unit = "cycles/px"],
        /// Butterworth order n (1..=32); used only by kind "butterworth".
        order: u32 = 2 => [min = 1, max = 32],
    }
}

/// Fourier-domain low/high-pass filter (`filter.frequency_filter`). See [`frequency_filter`].
#[derive(Debug, Clone, PartialEq)]
pub struct FrequencyFilter {
    kind: FilterKind,
    pass: PassBand,
    cutoff: f64,
    order: u32,
}

impl Op for FrequencyFilter {
    type Params = FrequencyFilterParams;
    const ID: &'static str = "filter.frequency_filter";
    const SUMMARY: &'static str =
        "Low- or high-pass filters an image in the Fourier domain (ideal, Gaussian, Butterworth).";
    const DOC: &'static str = r#"
Multiplies the 2-D DFT of every channel by a radial transfer function and transforms back:
`out = IDFT(H(D) · DFT(in))`, with `D(u, v) = √(fu² + fv²)` the frequency in cycles per pixel
(`fu = min(u, W − u)/W`, `fv = min(v, H − v)/H`) and the cutoff D0 in the same unit:
- ideal: H_low = 1 if D ≤ D0, else 0;
- gaussian: H_low = exp(−D²/(2·D0²)) (a Gaussian blur of σ = 1/(2π·D0) px with a wrap border);
- butterworth: H_low = 1/(1 + (D/D0)^(2n)), n = `order`.
High-pass is `1 − H_low`, so low + high = the input. The filter is circular (the image is one
period of a periodic signal), so content wraps around the edges. The output is f32 with the
input's channels for every input depth (u8/u16 values taken as they are, not rescaled).

Method: real-input FFT in f32 (rustfft; pairs of rows per complex FFT, half spectrum only),
multiply, real-output inverse FFT, scale 1/(W·H). Any size. OpenCV has no such function; this
is the textbook construction (numpy: `ifft2(H * fft2(img)).real`).

Reference: R. C. Gonzalez, R. E. Woods, "Digital Image Processing", 4th ed., §4.8–4.9
(ideal, Butterworth and Gaussian low/high-pass filters).

Example:
    "smooth": (op: "filter.frequency_filter", inputs: { "image": "gray.image" }, params: (kind: "gaussian", pass: "low", cutoff: 0.05)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to filter, any pixel format (each channel on its own).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The filtered image, f32, same size and channels as the input.",
        )]
    }

    fn new(params: FrequencyFilterParams) -> Result<Self, String> {
        let FrequencyFilterParams {
            kind,
            pass,
            cutoff,
            order,
        } = params;
        if !(cutoff > 0.0 && cutoff <= MAX_CUTOFF) {
            return Err(format!(
                "`cutoff` must be in (0, {MAX_CUTOFF}] cycles/px, got {cutoff}"
            ));
        }
        if !(1..=MAX_ORDER).contains(&order) {
            return Err(format!(
                "`order` must be between 1 and {MAX_ORDER}, got {order}"
            ));
        }
        Ok(FrequencyFilter {
            kind,
            pass,
            cutoff,
            order,
        })
    }
}

impl Operator for FrequencyFilter {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = frequency_filter(image, self.kind, self.pass, self.cutoff, self.order)
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// The low-pass transfer function at radial frequency `d` (cycles/px).
fn low_pass(kind: FilterKind, d: f64, cutoff: f64, order: u32) -> f64 {
    match kind {
        FilterKind::Ideal => {
            if d <= cutoff {
                1.0
            } else {
                0.0
            }
        }
        FilterKind::Gaussian => (-d * d / (2.0 * cutoff * cutoff)).exp(),
        FilterKind::Butterworth => 1.0 / (1.0 + (d / cutoff).powi(2 * order as i32)),
    }
}

/// The transfer function `H(D)` (see the operator docs) at radial frequency `d` cycles/px.
pub fn transfer(kind: FilterKind, pass: PassBand, d: f64, cutoff: f64, order: u32) -> f64 {
    let low = low_pass(kind, d, cutoff, order);
    match pass {
        PassBand::Low => low,
        PassBand::High => 1.0 - low,
    }
}

/// Filters every channel of `image` in the Fourier domain (see the operator docs); the output
/// is f32 with the input's size and channels. `cutoff` is in cycles per pixel.
pub fn frequency_filter(
    image: &Image,
    kind: FilterKind,
    pass: PassBand,
    cutoff: f64,
    order: u32,
) -> Result<Image, ValueError> {
    let (w, h) = (image.width(), image.height());
    let planes = to_planes(image)
        .iter()
        .map(|plane| filter_plane(plane, w, h, kind, pass, cutoff, order))
        .collect();
    from_planes(w, h, image.channels(), planes)
}

/// [`frequency_filter`] of one `w × h` f32 plane.
pub fn filter_plane(
    plane: &[f32],
    w: usize,
    h: usize,
    kind: FilterKind,
    pass: PassBand,
    cutoff: f64,
    order: u32,
) -> Vec<f32> {
    if w == 0 || h == 0 {
        return Vec::new();
    }
    let mut planner = FftPlanner::<f32>::new();
    let mut columns = real_spectrum_half(&mut planner, plane, w, h);
    let scale = 1.0 / (w * h) as f64;
    // Squared vertical frequencies, shared by every column spectrum.
    let fv2: Vec<f64> = (0..h)
        .map(|v| {
            let f = v.min(h - v) as f64 / h as f64;
            f * f
        })
        .collect();
    let gaussian_v: Vec<f64> = fv2
        .iter()
        .map(|&f2| (-f2 / (2.0 * cutoff * cutoff)).exp())
        .collect();
    // Row u of `columns` is F(u, 0..H), u ≤ W/2, so fu = u/W.
    columns.par_chunks_mut(h).enumerate().for_each_init(
        || vec![0.0f32; h],
        |gains, (u, row)| {
            let fu = u as f64 / w as f64;
            if kind == FilterKind::Gaussian {
                // Separable: exp(−(fu² + fv²)/2D0²) = exp(−fu²/2D0²) · exp(−fv²/2D0²).
                let gu = (-fu * fu / (2.0 * cutoff * cutoff)).exp();
                for (g, &gv) in gains.iter_mut().zip(&gaussian_v) {
                    let low = gu * gv;
                    let h = match pass {
                        PassBand::Low => low,
                        PassBand::High => 1.0 - low,
                    };
                    *g = (h * scale) as f32;
                }
            } else {
                for (g, &fv2) in gains.iter_mut().zip(&fv2) {
                    let d = (fu * fu + fv2).sqrt();
                    *g = (transfer(kind, pass, d, cutoff, order) * scale) as f32;
                }
            }
            for (z, &g) in row.iter_mut().zip(gains.iter()) {
                *z *= g;
            }
        },
    );
    real_from_spectrum_half(&mut planner, columns, w, h)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::border::BorderMode;
    use crate::filter::gaussian::gaussian_blur;
    use crate::filter::test_support::{random_u8, randoms};
    use ocellus_engine::value::Channels;
    use proptest::prelude::*;

    const KINDS: [FilterKind; 3] = [
        FilterKind::Ideal,
        FilterKind::Gaussian,
        FilterKind::Butterworth,
    ];

    fn plane(w: usize, h: usize, seed: u64) -> Vec<f32> {
        randoms(seed, w * h)
            .iter()
            .map(|&r| (r * 255.0) as f32)
            .collect()
    }

    #[test]
    fn constant_image_is_kept_by_low_and_zeroed_by_high() {
        let (w, h) = (13, 10);
        let c = vec![77.0f32; w * h];
        for kind in KINDS {
            let low = filter_plane(&c, w, h, kind, PassBand::Low, 0.05, 2);
            let high = filter_plane(&c, w, h, kind, PassBand::High, 0.05, 2);
            assert!(low.iter().all(|&v| (v - 77.0).abs() < 1e-3), "{kind:?}");
            assert!(high.iter().all(|&v| v.abs() < 1e-3), "{kind:?}");
        }
    }

    #[test]
    fn low_pass_preserves_the_mean() {
        let (w, h) = (31, 17);
        let p = plane(w, h, 4);
        let mean = |v: &[f32]| v.iter().map(|&x| f64::from(x)).sum::<f64>() / v.len() as f64;
        for kind in KINDS {
            let low = filter_plane(&p, w, h, kind, PassBand::Low, 0.02, 3);
            assert!((mean(&low) - mean(&p)).abs() < 1e-3, "{kind:?}");
            let high = filter_plane(&p, w, h, kind, PassBand::High, 0.02, 3);
            assert!(mean(&high).abs() < 1e-3, "{kind:?}");
        }
    }

    #[test]
    fn ideal_cutoff_above_the_corner_passes_everything() {
        let (w, h) = (9, 8);
        let p = plane(w, h, 5);
        let out = filter_plane(&p, w, h, FilterKind::Ideal, PassBand::Low, 0.75, 1);
        for (a, b) in out.iter().zip(&p) {
            assert!((a - b).abs() < 1e-3);
        }
        // A pure cosine at 0.25 cycles/px along x survives a cutoff of 0.3 and not 0.2.
        let (w, h) = (16, 4);
        let cosine: Vec<f32> = (0..w * h)
            .map(|i| (std::f32::consts::FRAC_PI_2 * (i % w) as f32).cos())
            .collect();
        let kept = filter_plane(&cosine, w, h, FilterKind::Ideal, PassBand::Low, 0.3, 1);
        let gone = filter_plane(&cosine, w, h, FilterKind::Ideal, PassBand::Low, 0.2, 1);
        for i in 0..w * h {
            assert!((kept[i] - cosine[i]).abs() < 1e-5);
            assert!(gone[i].abs() < 1e-5);
        }
        // Butterworth at D = D0 halves it; Gaussian at D = D0 scales it by e^(−1/2).
        let half = filter_plane(
            &cosine,
            w,
            h,
            FilterKind::Butterworth,
            PassBand::Low,
            0.25,
            4,
        );
        let g = filter_plane(&cosine, w, h, FilterKind::Gaussian, PassBand::Low, 0.25, 1);
        for i in 0..w * h {
            assert!((half[i] - 0.5 * cosine[i]).abs() < 1e-5);
            assert!((g[i] - (-0.5f32).exp() * cosine[i]).abs() < 1e-5);
        }
    }

    #[test]
    fn gaussian_low_pass_matches_a_wrapped_spatial_blur() {
        let (w, h) = (64, 48);
        let img = random_u8(w, h, Channels::Gray, 2);
        let sigma = 2.0;
        let spatial = gaussian_blur(
            &super::super::from_planes(w, h, Channels::Gray, to_planes(&img)).unwrap(),
            sigma,
            sigma,
            41,
            41,
            BorderMode::Wrap,
            0.0,
        );
        let cutoff = 1.0 / (2.0 * std::f64::consts::PI * sigma);
        let out = frequency_filter(&img, FilterKind::Gaussian, PassBand::Low, cutoff, 1).unwrap();
        let diff = out
            .as_f32()
            .unwrap()
            .iter()
            .zip(spatial.as_f32().unwrap())
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        // The sampled kernel's spectrum differs from the continuous Gaussian by aliasing only.
        assert!(diff < 0.05, "max difference {diff} gray levels");
    }

    #[test]
    fn colour_channels_are_filtered_independently() {
        let (w, h) = (12, 7);
        let img = random_u8(w, h, Channels::Rgb, 6);
        let out = frequency_filter(&img, FilterKind::Butterworth, PassBand::High, 0.1, 2).unwrap();
        assert_eq!(
            (out.width(), out.height(), out.channels()),
            (w, h, Channels::Rgb)
        );
        let planes = to_planes(&img);
        let outs = to_planes(&out);
        for c in 0..3 {
            let alone = filter_plane(
                &planes[c],
                w,
                h,
                FilterKind::Butterworth,
                PassBand::High,
                0.1,
                2,
            );
            assert_eq!(alone, outs[c]);
        }
        let empty = Image::from_u16(0, 3, Channels::Rgba, vec![]).unwrap();
        let out = frequency_filter(&empty, FilterKind::Ideal, PassBand::Low, 0.1, 1).unwrap();
        assert_eq!((out.width(), out.height()), (0, 3));
    }

    #[test]
    fn params_are_checked() {
        let p = |cutoff: f64, order: u32| {
            FrequencyFilter::new(FrequencyFilterParams {
                cutoff,
                order,
                ..Default::default()
            })
        };
        assert!(p(0.1, 2).is_ok());
        for bad in [0.0, -0.1, 1.5, f64::NAN, f64::INFINITY] {
            assert!(p(bad, 2).unwrap_err().contains("cutoff"));
        }
        assert!(p(0.1, 0).unwrap_err().contains("order"));
        assert!(p(0.1, 33).unwrap_err().contains("order"));
    }

    #[test]
    fn output_is_identical_for_any_thread_count() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let img = random_u8(201, 77, Channels::Rgb, 1);
        let run = || frequency_filter(&img, FilterKind::Gaussian, PassBand::High, 0.07, 1).unwrap();
        assert_eq!(pool(1).install(run), pool(3).install(run));
    }

    fn any_kind() -> impl Strategy<Value = FilterKind> {
        prop::sample::select(KINDS.to_vec())
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        #[test]
        fn low_plus_high_is_the_identity(
            w in 1usize..33,
            h in 1usize..33,
            kind in any_kind(),
            cutoff in 0.01f64..0.7,
            order in 1u32..6,
            seed in any::<u64>(),
        ) {
            let p = plane(w, h, seed);
            let low = filter_plane(&p, w, h, kind, PassBand::Low, cutoff, order);
            let high = filter_plane(&p, w, h, kind, PassBand::High, cutoff, order);
            for i in 0..w * h {
                prop_assert!((low[i] + high[i] - p[i]).abs() < 1e-4 * 255.0, "{} + {} vs {}", low[i], high[i], p[i]);
            }
        }
    }
}
