//! `texture.efros_leung`: non-parametric pixel-wise texture synthesis (Efros & Leung 1999).
//!
//! [`synthesize`] grows the output from a seed patch of the source: each unfilled pixel on the
//! growing front, most-constrained first, takes the centre of a source window chosen at random
//! among those whose Gaussian-weighted SSD to its known neighbourhood is within (1 + ε) of the
//! best.
//!
//! Determinism: for each pixel the errors of all source windows are computed in parallel over
//! source rows (each error a sequential sum, the same on any thread) and collected in order;
//! the fill order and the random choices are sequential, from one seeded generator.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::value::Metrics;
use rayon::prelude::*;

use super::quilting::choose_within;
use super::{Texture, check_output_side, source_port, synthesis_outputs, synthesis_ports};
use crate::video::filters::SplitMix64;

/// Efros & Leung's Gaussian: σ = window / 6.4.
const SIGMA_PER_WINDOW: f64 = 1.0 / 6.4;

params! {
    /// Parameters of `texture.efros_leung`.
    pub struct EfrosLeungParams {
        /// Output width, px (1..=4096).
        width: u32 = 64 => [min = 1, max = 4096, unit = "px"],
        /// Output height, px (1..=4096).
        height: u32 = 64 => [min = 1, max = 4096, unit = "px"],
        /// Neighbourhood window side, px (odd, ≥ 3, at most the source's shorter side). The
        /// speed–quality knob: the cost grows with its square, and it should span the
        /// texture's largest regular feature.
        window_px: u32 = 11 => [min = 3, unit = "px"],
        /// ε: candidates are the source windows with error ≤ (1 + ε) · the best (≥ 0; the
        /// paper uses 0.1).
        error_threshold: f64 = 0.1 => [min = 0.0],
        /// Side of the seed patch copied from a random place of the source to the output's
        /// centre, px (≥ 1, at most the source's shorter side).
        seed_px: u32 = 3 => [min = 1, unit = "px"],
        /// Seed of the random choices (seed patch and choice among candidates).
        seed: u64 = 0,
    }
}

/// Settings of [`synthesize`] (see [`EfrosLeungParams`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EfrosLeungConfig {
    /// Output width, px.
    pub width: usize,
    /// Output height, px.
    pub height: usize,
    /// Window side, px (odd).
    pub window_px: usize,
    /// ε.
    pub error_threshold: f64,
    /// Seed patch side, px.
    pub seed_px: usize,
    /// Random seed.
    pub seed: u64,
}

/// Efros–Leung synthesis (`texture.efros_leung`). See [`synthesize`].
#[derive(Debug, Clone, PartialEq)]
pub struct EfrosLeung {
    config: EfrosLeungConfig,
}

impl Op for EfrosLeung {
    type Params = EfrosLeungParams;
    const ID: &'static str = "texture.efros_leung";
    const SUMMARY: &'static str = "Synthesizes a texture pixel by pixel from a sample by non-parametric neighbourhood matching.";
    const DOC: &'static str = r#"
Non-parametric sampling of A. A. Efros and T. K. Leung, "Texture Synthesis by Non-parametric
Sampling", ICCV 1999.

A `seed_px` square from a random place of the source is copied to the centre of the output
(`width` × `height`, the source's channels and depth). Then, pass after pass, the unfilled
pixels with at least one filled 8-neighbour are sorted by their number of filled pixels in the
`window_px` × `window_px` window around them (most first, then raster order) and filled in that
order: the window's known pixels are compared with every full window of the source by

    d(s) = Σ G(o)·m(o)·‖out(p + o) − src(s + o)‖² / Σ G(o)·m(o),

G a Gaussian of σ = window/6.4, m(o) = 1 where the output pixel is filled (pixels outside the
output are unknown); a window is drawn uniformly among those with d ≤ (1 + `error_threshold`) ·
the smallest d, and its centre pixel is copied. Every output pixel is a source pixel.

Outputs `image` and `metrics`: `pixels_synthesized`; `match_rms` = √(mean chosen d per
channel), image units; `candidates_mean`, the mean number of windows drawn among;
`patch_match_rms` = RMS distance of the output's 7×7 patches (at most 1024) to their nearest
source patch.

Cost: output pixels × source windows × known window pixels (about 64² · 54² · 121 ≈ 1.4·10⁹
multiply-adds for 64×64 from 64×64 with an 11 px window): slow by nature. `window_px` is the
speed–quality knob. Deterministic for
a seed at any thread count.

Example:
    "grow": (op: "texture.efros_leung", inputs: { "source": "tex.image" },
             params: (width: 48, height: 48, window_px: 9, seed: 2)),
"#;

    fn inputs() -> Vec<PortSpec> {
        source_port("window_px")
    }

    fn outputs() -> Vec<PortSpec> {
        synthesis_ports("pixels_synthesized, match_rms, candidates_mean")
    }

    fn new(params: EfrosLeungParams) -> Result<Self, String> {
        let EfrosLeungParams {
            width,
            height,
            window_px,
            error_threshold,
            seed_px,
            seed,
        } = params;
        check_output_side("width", width)?;
        check_output_side("height", height)?;
        if window_px < 3 || window_px.is_multiple_of(2) {
            return Err(format!(
                "`window_px` must be odd and at least 3, got {window_px}"
            ));
        }
        if !(error_threshold.is_finite() && error_threshold >= 0.0) {
            return Err(format!(
                "`error_threshold` must be finite and ≥ 0, got {error_threshold}"
            ));
        }
        if seed_px == 0 {
            return Err("`seed_px` must be at least 1".into());
        }
        Ok(EfrosLeung {
            config: EfrosLeungConfig {
                width: width as usize,
                height: height as usize,
                window_px: window_px as usize,
                error_threshold,
                seed_px: seed_px as usize,
                seed,
            },
        })
    }
}

impl Operator for EfrosLeung {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("source")?;
        let source = Texture::from_image(image, "source")?;
        let result = synthesize(&source, &self.config).map_err(|e| OpError::input("source", e))?;
        let mut metrics = Metrics::new();
        metrics.insert(
            "pixels_synthesized".into(),
            result.pixels_synthesized as f64,
        );
        metrics.insert("match_rms".into(), result.match_rms);
        metrics.insert("candidates_mean".into(), result.candidates_mean);
        synthesis_outputs(&result.texture, &source, image, metrics)
    }
}

/// The result of [`synthesize`].
#[derive(Debug, Clone, PartialEq)]
pub struct Synthesis {
    /// The synthesized texture.
    pub texture: Texture,
    /// Pixels filled by matching (all but the seed patch).
    pub pixels_synthesized: usize,
    /// √(mean chosen weighted SSD per channel), image units.
    pub match_rms: f64,
    /// Mean number of candidate windows drawn among.
    pub candidates_mean: f64,
}

/// Synthesizes a `config.width × config.height` texture from `source` by Efros–Leung
/// sampling (see [`EfrosLeung`]). Errors when the source is smaller than the window or the
/// seed patch.
pub fn synthesize(source: &Texture, config: &EfrosLeungConfig) -> Result<Synthesis, String> {
    let n = config.window_px;
    if n == 0 || n.is_multiple_of(2) {
        return Err(format!("window of {n} px is not odd"));
    }
    let half = n / 2;
    let side = source.width.min(source.height);
    if side < n || side < config.seed_px || config.seed_px == 0 {
        return Err(format!(
            "is {}×{}, smaller than the {n} px window or the {} px seed patch",
            source.width, source.height, config.seed_px
        ));
    }
    let (w, h, c) = (config.width, config.height, source.channels);
    let sigma = n as f64 * SIGMA_PER_WINDOW;
    let gauss: Vec<f64> = (0..n * n)
        .map(|i| {
            let dx = (i % n) as f64 - half as f64;
            let dy = (i / n) as f64 - half as f64;
            (-(dx * dx + dy * dy) / (2.0 * sigma * sigma)).exp()
        })
        .collect();
    let mut rng = SplitMix64::new(config.seed);
    let mut out = Texture::zeros(w, h, c);
    let mut filled = vec![false; w * h];
    // Seed patch at the centre, clipped to the output.
    let s = config.seed_px;
    let sx0 = ((rng.uniform() * (source.width - s + 1) as f64) as usize).min(source.width - s);
    let sy0 = ((rng.uniform() * (source.height - s + 1) as f64) as usize).min(source.height - s);
    let (ox0, oy0) = ((w / 2).saturating_sub(s / 2), (h / 2).saturating_sub(s / 2));
    for dy in 0..s.min(h - oy0) {
        for dx in 0..s.min(w - ox0) {
            out.pixel_mut(ox0 + dx, oy0 + dy)
                .copy_from_slice(source.pixel(sx0 + dx, sy0 + dy));
            filled[(oy0 + dy) * w + ox0 + dx] = true;
        }
    }
    let (cw, ch) = (source.width - n + 1, source.height - n + 1);
    let (mut match_sum, mut candidate_sum, mut synthesized) = (0.0f64, 0usize, 0usize);
    let window = |x: usize, y: usize| {
        let (x0, y0) = (x as isize - half as isize, y as isize - half as isize);
        (0..n * n).filter_map(move |i| {
            let (ox, oy) = (x0 + (i % n) as isize, y0 + (i / n) as isize);
            (ox >= 0 && oy >= 0 && (ox as usize) < w && (oy as usize) < h).then_some((
                i,
                ox as usize,
                oy as usize,
            ))
        })
    };
    loop {
        let mut front: Vec<(usize, usize)> = (0..w * h)
            .filter(|&i| !filled[i] && has_filled_neighbour(&filled, w, h, i % w, i / w))
            .map(|i| {
                let known = window(i % w, i / w)
                    .filter(|&(_, ox, oy)| filled[oy * w + ox])
                    .count();
                (i, known)
            })
            .collect();
        if front.is_empty() {
            break;
        }
        front.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        for (i, _) in front {
            let (x, y) = (i % w, i / w);
            // Known pixels of the window: (window index, output sample offset, weight).
            let known: Vec<(usize, usize, f64)> = window(x, y)
                .filter(|&(_, ox, oy)| filled[oy * w + ox])
                .map(|(k, ox, oy)| (k, (oy * w + ox) * c, gauss[k]))
                .collect();
            let weight: f64 = known.iter().map(|k| k.2).sum();
            let errors: Vec<f64> = (0..ch)
                .into_par_iter()
                .flat_map_iter(|sy| {
                    let (known, out) = (&known, &out);
                    (0..cw).map(move |sx| {
                        let mut ssd = 0.0f64;
                        for &(k, o, g) in known {
                            let src = ((sy + k / n) * source.width + sx + k % n) * c;
                            let d: f64 = out.samples[o..o + c]
                                .iter()
                                .zip(&source.samples[src..src + c])
                                .map(|(a, b)| f64::from(a - b).powi(2))
                                .sum();
                            ssd += g * d;
                        }
                        ssd / weight
                    })
                })
                .collect();
            let best = errors.iter().copied().fold(f64::INFINITY, f64::min);
            let limit = best * (1.0 + config.error_threshold);
            candidate_sum += errors.iter().filter(|&&e| e <= limit).count();
            let chosen = choose_within(&errors, config.error_threshold, &mut rng);
            let (sx, sy) = (chosen % cw + half, chosen / cw + half);
            out.pixel_mut(x, y).copy_from_slice(source.pixel(sx, sy));
            filled[i] = true;
            match_sum += errors[chosen] / c as f64;
            synthesized += 1;
        }
    }
    let mean = |sum: f64| {
        if synthesized == 0 {
            0.0
        } else {
            sum / synthesized as f64
        }
    };
    Ok(Synthesis {
        texture: out,
        pixels_synthesized: synthesized,
        match_rms: mean(match_sum).sqrt(),
        candidates_mean: mean(candidate_sum as f64),
    })
}

/// True when a pixel of the 8-neighbourhood of (x, y) is filled.
fn has_filled_neighbour(filled: &[bool], w: usize, h: usize, x: usize, y: usize) -> bool {
    (y.saturating_sub(1)..(y + 2).min(h))
        .any(|yy| (x.saturating_sub(1)..(x + 2).min(w)).any(|xx| filled[yy * w + xx]))
}

#[cfg(test)]
mod tests {
    use super::super::test_support::{blobs, noise, periodic};
    use super::super::{channel_moments, patch_match_rms};
    use super::*;

    fn config(width: usize, height: usize, window_px: usize) -> EfrosLeungConfig {
        EfrosLeungConfig {
            width,
            height,
            window_px,
            error_threshold: 0.1,
            seed_px: 3,
            seed: 7,
        }
    }

    #[test]
    fn every_pixel_is_filled_from_the_source() {
        let source = noise(16, 16, 4);
        let result = synthesize(&source, &config(20, 18, 5)).unwrap();
        assert_eq!(result.pixels_synthesized, 20 * 18 - 9);
        let values: std::collections::BTreeSet<u32> =
            source.samples.iter().map(|v| v.to_bits()).collect();
        assert!(
            result
                .texture
                .samples
                .iter()
                .all(|v| values.contains(&v.to_bits()))
        );
    }

    #[test]
    fn periodic_texture_is_continued_exactly() {
        // With ε = 0 and a window covering a period, only exact continuations match.
        let source = periodic(24, 24, 4, 3);
        let result = synthesize(
            &source,
            &EfrosLeungConfig {
                error_threshold: 0.0,
                ..config(20, 20, 5)
            },
        )
        .unwrap();
        assert_eq!(result.match_rms, 0.0);
        let out = &result.texture;
        for y in 0..20 {
            for x in 0..16 {
                assert_eq!(out.pixel(x, y), out.pixel(x + 4, y));
            }
        }
    }

    #[test]
    fn output_statistics_match_the_source() {
        let source = blobs(32, 32, 8);
        let result = synthesize(&source, &config(36, 36, 9)).unwrap();
        let out = &result.texture;
        let (sm, sv) = channel_moments(&source)[0];
        let (om, ov) = channel_moments(out)[0];
        assert!((sm - om).abs() < 0.35 * sv.sqrt(), "means {sm} {om}");
        assert!((ov / sv - 1.0).abs() < 0.5, "variances {sv} {ov}");
        let rms = patch_match_rms(out, &source, 5, 3).unwrap();
        let baseline = patch_match_rms(&noise(36, 36, 1), &source, 5, 3).unwrap();
        assert!(rms < 0.3 * baseline, "{rms} vs noise {baseline}");
    }

    #[test]
    fn same_result_for_one_and_many_threads() {
        let source = blobs(24, 24, 2);
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| synthesize(&source, &config(24, 20, 7)).unwrap())
        };
        assert_eq!(run(1), run(3));
    }

    #[test]
    fn bad_inputs_are_rejected() {
        assert!(synthesize(&blobs(6, 6, 1), &config(10, 10, 7)).is_err());
        for params in [
            EfrosLeungParams {
                window_px: 8,
                ..Default::default()
            },
            EfrosLeungParams {
                error_threshold: f64::INFINITY,
                ..Default::default()
            },
            EfrosLeungParams {
                height: 0,
                ..Default::default()
            },
            EfrosLeungParams {
                seed_px: 0,
                ..Default::default()
            },
        ] {
            assert!(EfrosLeung::new(params).is_err());
        }
    }
}
