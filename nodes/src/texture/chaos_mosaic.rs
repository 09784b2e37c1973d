//! `texture.chaos_mosaic`: the chaos mosaic of Xu, Guo & Shum (2000).
//!
//! [`chaos_mosaic`] tiles the source over the output, then pastes randomly chosen source
//! blocks at positions visited by Arnold's cat map ([`cat_map`]), joined by feathering or by
//! minimum-error boundary cuts, which breaks the tiling's visible period.
//!
//! Determinism: everything is sequential and driven by one seeded generator; the only
//! parallel step is the final metric, which is reduced in a fixed order.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::value::Metrics;
use ocellus_engine::{param_enum, params};

use super::quilting::{min_cut_path, pixel_ssd};
use super::{Texture, check_output_side, source_port, synthesis_outputs, synthesis_ports};
use crate::video::filters::SplitMix64;

param_enum! {
    /// How a pasted block meets what is under it.
    pub enum MosaicBoundary {
        /// Linear cross-fade over `boundary_px` at the block's edges.
        Feather = "feather",
        /// Minimum-error boundary cut inside strips of `boundary_px` along the four edges
        /// (every output pixel stays a source pixel).
        Cut = "cut",
    }
}

params! {
    /// Parameters of `texture.chaos_mosaic`.
    pub struct ChaosMosaicParams {
        /// Output width, px (1..=4096, at least `block_px`).
        width: u32 = 128 => [min = 1, max = 4096, unit = "px"],
        /// Output height, px (1..=4096, at least `block_px`).
        height: u32 = 128 => [min = 1, max = 4096, unit = "px"],
        /// Blocks pasted (≥ 0; 0 gives the plain tiling).
        iterations: u32 = 64 => [min = 0],
        /// Pasted block side, px (≥ 2, at most the source's and the output's shorter side).
        block_px: u32 = 16 => [min = 2, unit = "px"],
        /// Boundary treatment: "feather" or "cut".
        boundary: MosaicBoundary = MosaicBoundary::Feather,
        /// Width of the feather ramp or of the cut strips, px (0 ≤ boundary_px ≤ block_px/2;
        /// 0 pastes hard-edged blocks).
        boundary_px: u32 = 3 => [min = 0, unit = "px"],
        /// Seed of the random choices (source blocks and the cat map's starting point).
        seed: u64 = 0,
    }
}

/// Settings of [`chaos_mosaic`] (see [`ChaosMosaicParams`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MosaicConfig {
    /// Output width, px.
    pub width: usize,
    /// Output height, px.
    pub height: usize,
    /// Blocks pasted.
    pub iterations: usize,
    /// Block side, px.
    pub block_px: usize,
    /// Boundary treatment.
    pub boundary: MosaicBoundary,
    /// Feather ramp or cut strip width, px.
    pub boundary_px: usize,
    /// Random seed.
    pub seed: u64,
}

/// Chaos mosaic (`texture.chaos_mosaic`). See [`chaos_mosaic`].
#[derive(Debug, Clone, PartialEq)]
pub struct ChaosMosaic {
    config: MosaicConfig,
}

impl Op for ChaosMosaic {
    type Params = ChaosMosaicParams;
    const ID: &'static str = "texture.chaos_mosaic";
    const SUMMARY: &'static str =
        "Synthesizes a texture by tiling the source and pasting blocks at cat-map positions.";
    const DOC: &'static str = r#"
The chaos mosaic of Y.-Q. Xu, B. Guo and H.-Y. Shum, "Chaos Mosaic: Fast and Memory
Efficient Texture Synthesis", Microsoft Research MSR-TR-2000-32 (2000).

The output (`width` × `height`, the source's channels and depth) starts as the source tiled
from the top-left corner. Then `iterations` times a `block_px` square is taken from a uniformly
random place of the source and pasted with its top-left corner at the next point of Arnold's cat
map on the torus of block positions (M × N with M = width − block + 1, N = height − block + 1):

    (x, y) ↦ ((x + y) mod M, (x + 2y) mod N),

starting from a random point (the map is a bijection when M = N; its orbits spread the blocks
chaotically over the output). With `boundary: "feather"` the block is cross-faded: weight
min(1, (e + 1)/(boundary_px + 1)), e the distance in pixels to the block's nearest edge. With
`"cut"` the block keeps only the pixels inside four minimum-error boundary cuts (dynamic
programming as in image quilting) through strips of `boundary_px` along its edges.

Outputs `image` and `metrics`: `blocks`; `distinct_positions` visited by the map;
`period_rms` = RMS difference between the output and itself shifted by one source size (0 for
the plain tiling: how much of the tiling's period is broken), image units; `patch_match_rms`
= RMS distance of the output's 7×7 patches (at most 1024) to their nearest source patch.
Cost: the synthesis is iterations × block area, independent of the source size (that is the
method's point); the `patch_match_rms` metric compares output patches with every source
patch, so it grows with the source's area. Deterministic for a seed.

Example:
    "mosaic": (op: "texture.chaos_mosaic", inputs: { "source": "tex.image" },
               params: (width: 128, height: 128, iterations: 64, block_px: 16, seed: 3)),
"#;

    fn inputs() -> Vec<PortSpec> {
        source_port("block_px")
    }

    fn outputs() -> Vec<PortSpec> {
        synthesis_ports("blocks, distinct_positions, period_rms")
    }

    fn new(params: ChaosMosaicParams) -> Result<Self, String> {
        let ChaosMosaicParams {
            width,
            height,
            iterations,
            block_px,
            boundary,
            boundary_px,
            seed,
        } = params;
        check_output_side("width", width)?;
        check_output_side("height", height)?;
        if block_px < 2 || block_px > width.min(height) {
            return Err(format!(
                "`block_px` must be at least 2 and at most the output's shorter side ({}), got {block_px}",
                width.min(height)
            ));
        }
        if boundary_px > block_px / 2 {
            return Err(format!(
                "`boundary_px` must be at most half of `block_px` ({}), got {boundary_px}",
                block_px / 2
            ));
        }
        Ok(ChaosMosaic {
            config: MosaicConfig {
                width: width as usize,
                height: height as usize,
                iterations: iterations as usize,
                block_px: block_px as usize,
                boundary,
                boundary_px: boundary_px as usize,
                seed,
            },
        })
    }
}

impl Operator for ChaosMosaic {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("source")?;
        let source = Texture::from_image(image, "source")?;
        let result =
            chaos_mosaic(&source, &self.config).map_err(|e| OpError::input("source", e))?;
        let mut metrics = Metrics::new();
        metrics.insert("blocks".into(), self.config.iterations as f64);
        metrics.insert(
            "distinct_positions".into(),
            result.distinct_positions as f64,
        );
        metrics.insert(
            "period_rms".into(),
            period_rms(&result.texture, source.width, source.height),
        );
        synthesis_outputs(&result.texture, &source, image, metrics)
    }
}

/// The result of [`chaos_mosaic`].
#[derive(Debug, Clone, PartialEq)]
pub struct Mosaic {
    /// The synthesized texture.
    pub texture: Texture,
    /// Block positions (top-left corners) in paste order.
    pub positions: Vec<(usize, usize)>,
    /// Distinct positions among them.
    pub distinct_positions: usize,
}

/// One step of Arnold's cat map on an `m × n` torus: (x, y) ↦ ((x + y) mod m, (x + 2y) mod n).
pub fn cat_map((x, y): (usize, usize), m: usize, n: usize) -> (usize, usize) {
    ((x + y) % m, (x + 2 * y) % n)
}

/// Synthesizes a `config.width × config.height` chaos mosaic of `source` (see
/// [`ChaosMosaic`]). Errors when the source or the output is smaller than a block.
pub fn chaos_mosaic(source: &Texture, config: &MosaicConfig) -> Result<Mosaic, String> {
    let b = config.block_px;
    let (w, h, c) = (config.width, config.height, source.channels);
    if b == 0 || source.width < b || source.height < b || w < b || h < b {
        return Err(format!(
            "is {}×{}: the source and the {w}×{h} output must be at least one {b} px block",
            source.width, source.height
        ));
    }
    let f = config.boundary_px.min(b / 2);
    let mut out = Texture::zeros(w, h, c);
    for y in 0..h {
        for x in 0..w {
            out.pixel_mut(x, y)
                .copy_from_slice(source.pixel(x % source.width, y % source.height));
        }
    }
    let mut rng = SplitMix64::new(config.seed);
    let (m, n) = (w - b + 1, h - b + 1);
    let draw = |rng: &mut SplitMix64, k: usize| ((rng.uniform() * k as f64) as usize).min(k - 1);
    let mut point = (draw(&mut rng, m), draw(&mut rng, n));
    let mut positions = Vec::with_capacity(config.iterations);
    let feather = (config.boundary == MosaicBoundary::Feather).then(|| feather_weights(b, f));
    for _ in 0..config.iterations {
        point = cat_map(point, m, n);
        let (px, py) = point;
        let sx = draw(&mut rng, source.width - b + 1);
        let sy = draw(&mut rng, source.height - b + 1);
        positions.push(point);
        let cut;
        let weights: &[f32] = match &feather {
            Some(w) => w,
            None => {
                cut = cut_mask(&out, source, (px, py), (sx, sy), b, f);
                &cut
            }
        };
        for y in 0..b {
            for x in 0..b {
                let a = weights[y * b + x];
                if a == 0.0 {
                    continue;
                }
                let src = source.pixel(sx + x, sy + y);
                for (o, &s) in out.pixel_mut(px + x, py + y).iter_mut().zip(src) {
                    *o = if a == 1.0 { s } else { *o + a * (s - *o) };
                }
            }
        }
    }
    let mut distinct = positions.clone();
    distinct.sort_unstable();
    distinct.dedup();
    Ok(Mosaic {
        texture: out,
        distinct_positions: distinct.len(),
        positions,
    })
}

/// Cross-fade weights of a `b × b` block with a ramp of `f` px.
fn feather_weights(b: usize, f: usize) -> Vec<f32> {
    (0..b * b)
        .map(|i| {
            let (x, y) = (i % b, i / b);
            let edge = x.min(y).min(b - 1 - x).min(b - 1 - y);
            ((edge + 1) as f32 / (f + 1) as f32).min(1.0)
        })
        .collect()
}

/// 0/1 mask of the block pixels inside the four minimum-error cuts through strips of `f` px.
fn cut_mask(
    out: &Texture,
    source: &Texture,
    (px, py): (usize, usize),
    (sx, sy): (usize, usize),
    b: usize,
    f: usize,
) -> Vec<f32> {
    let mut mask = vec![1.0f32; b * b];
    if f == 0 {
        return mask;
    }
    let diff =
        |x: usize, y: usize| pixel_ssd(out.pixel(px + x, py + y), source.pixel(sx + x, sy + y));
    // Left and right strips: vertical cuts; rows are block rows.
    for (x0, keep_right) in [(0, true), (b - f, false)] {
        let costs: Vec<f64> = (0..b)
            .flat_map(|y| (0..f).map(move |x| (x0 + x, y)))
            .map(|(x, y)| diff(x, y))
            .collect();
        let (path, _) = min_cut_path(&costs, b, f);
        for (y, &cut) in path.iter().enumerate() {
            for x in 0..f {
                if (keep_right && x < cut) || (!keep_right && x > cut) {
                    mask[y * b + x0 + x] = 0.0;
                }
            }
        }
    }
    // Top and bottom strips: horizontal cuts; rows are block columns.
    for (y0, keep_below) in [(0, true), (b - f, false)] {
        let costs: Vec<f64> = (0..b)
            .flat_map(|x| (0..f).map(move |y| (x, y0 + y)))
            .map(|(x, y)| diff(x, y))
            .collect();
        let (path, _) = min_cut_path(&costs, b, f);
        for (x, &cut) in path.iter().enumerate() {
            for y in 0..f {
                if (keep_below && y < cut) || (!keep_below && y > cut) {
                    mask[(y0 + y) * b + x] = 0.0;
                }
            }
        }
    }
    mask
}

/// RMS difference (image units) between `texture` and itself shifted by (`period_x`, 0) and
/// by (0, `period_y`), over the pixels where the shift stays inside; 0 when neither fits.
pub fn period_rms(texture: &Texture, period_x: usize, period_y: usize) -> f64 {
    let (mut sum, mut count) = (0.0f64, 0usize);
    for y in 0..texture.height {
        for x in 0..texture.width {
            let here = texture.pixel(x, y);
            if x + period_x < texture.width {
                sum += pixel_ssd(here, texture.pixel(x + period_x, y));
                count += texture.channels;
            }
            if y + period_y < texture.height {
                sum += pixel_ssd(here, texture.pixel(x, y + period_y));
                count += texture.channels;
            }
        }
    }
    if count == 0 {
        0.0
    } else {
        (sum / count as f64).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_support::{blobs, noise};
    use super::super::{channel_moments, patch_match_rms};
    use super::*;

    fn config(boundary: MosaicBoundary) -> MosaicConfig {
        MosaicConfig {
            width: 72,
            height: 72,
            iterations: 40,
            block_px: 12,
            boundary,
            boundary_px: 3,
            seed: 5,
        }
    }

    #[test]
    fn cat_map_is_a_bijection_on_a_square_torus() {
        assert_eq!(cat_map((1, 2), 7, 7), (3, 5));
        assert_eq!(cat_map((5, 6), 7, 7), (4, 3));
        let n = 13;
        let mut images: Vec<(usize, usize)> =
            (0..n * n).map(|i| cat_map((i % n, i / n), n, n)).collect();
        images.sort_unstable();
        images.dedup();
        assert_eq!(images.len(), n * n);
    }

    #[test]
    fn no_iterations_is_the_plain_tiling() {
        let source = blobs(24, 20, 1);
        let result = chaos_mosaic(
            &source,
            &MosaicConfig {
                iterations: 0,
                ..config(MosaicBoundary::Feather)
            },
        )
        .unwrap();
        assert_eq!(period_rms(&result.texture, 24, 20), 0.0);
        assert_eq!(result.texture.pixel(50, 45), source.pixel(2, 5));
    }

    #[test]
    fn mosaic_breaks_the_period_and_keeps_the_statistics() {
        let source = blobs(32, 32, 4);
        for boundary in [MosaicBoundary::Feather, MosaicBoundary::Cut] {
            let result = chaos_mosaic(&source, &config(boundary)).unwrap();
            let out = &result.texture;
            assert!(period_rms(out, 32, 32) > 10.0, "{boundary:?}");
            assert!(
                result.distinct_positions > 20,
                "{}",
                result.distinct_positions
            );
            let (sm, sv) = channel_moments(&source)[0];
            let (om, ov) = channel_moments(out)[0];
            assert!((sm - om).abs() < 0.15 * sv.sqrt(), "means {sm} {om}");
            assert!((ov / sv - 1.0).abs() < 0.3, "variances {sv} {ov}");
            let rms = patch_match_rms(out, &source, 7, 5).unwrap();
            let baseline = patch_match_rms(&noise(72, 72, 1), &source, 7, 5).unwrap();
            // Feathered seams blend pixels, so the bound is looser than quilting's.
            assert!(rms < 0.35 * baseline, "{rms} vs noise {baseline}");
        }
    }

    #[test]
    fn cut_boundaries_keep_source_pixels() {
        let source = noise(20, 20, 6);
        let result = chaos_mosaic(&source, &config(MosaicBoundary::Cut)).unwrap();
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
    fn bad_inputs_are_rejected() {
        assert!(chaos_mosaic(&blobs(8, 8, 1), &config(MosaicBoundary::Feather)).is_err());
        for params in [
            ChaosMosaicParams {
                block_px: 200,
                ..Default::default()
            },
            ChaosMosaicParams {
                boundary_px: 9,
                block_px: 16,
                ..Default::default()
            },
            ChaosMosaicParams {
                width: 0,
                ..Default::default()
            },
        ] {
            assert!(ChaosMosaic::new(params).is_err());
        }
    }
}
