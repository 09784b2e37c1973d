//! `texture.quilting`: image quilting (Efros & Freeman 2001).
//!
//! [`quilt`] lays square blocks of the source on a grid with overlaps, each block chosen at
//! random among the source blocks whose overlap error is within a tolerance of the best, and
//! joins it to its neighbours along minimum-error boundary cuts ([`min_cut_path`]).
//!
//! Determinism: the overlap errors of all candidate blocks are computed in parallel over source
//! rows (each error by the same sequential sum whatever thread runs it) and collected in order;
//! the choice among candidates draws from one seeded generator used sequentially.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::value::Metrics;
use rayon::prelude::*;

use super::{Texture, check_output_side, source_port, synthesis_outputs, synthesis_ports};
use crate::video::filters::SplitMix64;

params! {
    /// Parameters of `texture.quilting`.
    pub struct QuiltingParams {
        /// Output width, px (1..=4096).
        width: u32 = 128 => [min = 1, max = 4096, unit = "px"],
        /// Output height, px (1..=4096).
        height: u32 = 128 => [min = 1, max = 4096, unit = "px"],
        /// Block side, px (≥ 2, at most the source's shorter side). Larger blocks keep more
        /// of the source's structure and are faster (fewer blocks); smaller ones give more
        /// variety.
        block_px: u32 = 24 => [min = 2, unit = "px"],
        /// Overlap between neighbouring blocks, px (0 ≤ overlap < block; Efros & Freeman use
        /// a sixth of the block). 0 tiles random blocks without matching.
        overlap_px: u32 = 4 => [min = 0, unit = "px"],
        /// Candidates are the blocks with overlap error ≤ (1 + tolerance) · the best error
        /// (≥ 0; the paper uses 0.1). 0 keeps only the best blocks.
        tolerance: f64 = 0.1 => [min = 0.0],
        /// true: join blocks along the minimum-error boundary cut; false: straight seams
        /// (each new block overwrites the overlap).
        boundary_cut: bool = true,
        /// Seed of the random choices (first block and choice among candidates).
        seed: u64 = 0,
    }
}

/// Settings of [`quilt`] (see [`QuiltingParams`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QuiltConfig {
    /// Output width, px.
    pub width: usize,
    /// Output height, px.
    pub height: usize,
    /// Block side, px.
    pub block_px: usize,
    /// Overlap, px.
    pub overlap_px: usize,
    /// Relative tolerance on the overlap error.
    pub tolerance: f64,
    /// Minimum-error boundary cut (else straight seams).
    pub boundary_cut: bool,
    /// Random seed.
    pub seed: u64,
}

/// Image quilting (`texture.quilting`). See [`quilt`].
#[derive(Debug, Clone, PartialEq)]
pub struct Quilting {
    config: QuiltConfig,
}

impl Op for Quilting {
    type Params = QuiltingParams;
    const ID: &'static str = "texture.quilting";
    const SUMMARY: &'static str = "Synthesizes a larger texture by image quilting: overlapping blocks joined along minimum-error cuts.";
    const DOC: &'static str = r#"
Image quilting of A. A. Efros and W. T. Freeman, "Image Quilting for Texture Synthesis and
Transfer", SIGGRAPH 2001.

The output (`width` × `height`, the source's channels and depth) is covered by square blocks of
`block_px` laid on a grid of step `block_px − overlap_px`, in raster order. For each block every
source block position is scored by the sum of squared differences (all channels) with the
already synthesized pixels in its overlap (left strip, top strip, or both: the L shape). One
block is drawn uniformly among those with error ≤ (1 + `tolerance`) · the smallest error (the
first block uniformly among all). With `boundary_cut`, the block replaces the old pixels only on
its side of the minimum-error boundary cut: a path through the overlap's squared-difference
surface found by dynamic programming (E(i, j) = e(i, j) + min(E(i−1, j−1), E(i−1, j),
E(i−1, j+1)), traced back from the smallest end), vertical for the left strip, horizontal for
the top strip, both (the new block keeps the pixels on its side of both cuts) for the L shape.
Without it the block overwrites the overlap (straight seams).

Outputs `image` and `metrics`: `blocks`; `overlap_rms` = √(mean over blocks of the chosen
block's overlap SSD per sample), image units; `seam_rms` = RMS difference between the old and
the new block at the pixels where the output switches from one to the other (the cut, or the
straight edge), image units; `patch_match_rms` = RMS distance of the output's 7×7 patches (a
grid of at most 1024) to their nearest source patch, image units. Timing: run with `--profile`.

Cost: blocks × source positions × overlap area. Larger blocks and smaller overlaps are faster;
the cut lowers `seam_rms` at no search cost. Deterministic for a seed at any thread count.

Example:
    "quilt": (op: "texture.quilting", inputs: { "source": "tex.image" },
              params: (width: 128, height: 128, block_px: 24, overlap_px: 4, seed: 1)),
"#;

    fn inputs() -> Vec<PortSpec> {
        source_port("block_px")
    }

    fn outputs() -> Vec<PortSpec> {
        synthesis_ports("blocks, overlap_rms, seam_rms")
    }

    fn new(params: QuiltingParams) -> Result<Self, String> {
        let QuiltingParams {
            width,
            height,
            block_px,
            overlap_px,
            tolerance,
            boundary_cut,
            seed,
        } = params;
        check_output_side("width", width)?;
        check_output_side("height", height)?;
        if block_px < 2 {
            return Err(format!("`block_px` must be at least 2, got {block_px}"));
        }
        if overlap_px >= block_px {
            return Err(format!(
                "`overlap_px` ({overlap_px}) must be smaller than `block_px` ({block_px})"
            ));
        }
        if !(tolerance.is_finite() && tolerance >= 0.0) {
            return Err(format!(
                "`tolerance` must be finite and ≥ 0, got {tolerance}"
            ));
        }
        Ok(Quilting {
            config: QuiltConfig {
                width: width as usize,
                height: height as usize,
                block_px: block_px as usize,
                overlap_px: overlap_px as usize,
                tolerance,
                boundary_cut,
                seed,
            },
        })
    }
}

impl Operator for Quilting {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("source")?;
        let source = Texture::from_image(image, "source")?;
        let result = quilt(&source, &self.config).map_err(|e| OpError::input("source", e))?;
        let mut metrics = Metrics::new();
        metrics.insert("blocks".into(), result.blocks as f64);
        metrics.insert("overlap_rms".into(), result.overlap_rms);
        metrics.insert("seam_rms".into(), result.seam_rms);
        synthesis_outputs(&result.texture, &source, image, metrics)
    }
}

/// The result of [`quilt`].
#[derive(Debug, Clone, PartialEq)]
pub struct Quilt {
    /// The synthesized texture.
    pub texture: Texture,
    /// Blocks placed.
    pub blocks: usize,
    /// √(mean overlap SSD per sample of the chosen blocks), image units (0 without overlaps).
    pub overlap_rms: f64,
    /// RMS old/new difference at the seam pixels, image units (0 without seams).
    pub seam_rms: f64,
    /// Top-left source corner of every block, raster order.
    pub sources: Vec<(usize, usize)>,
}

/// Synthesizes a `config.width × config.height` texture from `source` by image quilting (see
/// [`Quilting`]). Errors when the source is smaller than a block.
pub fn quilt(source: &Texture, config: &QuiltConfig) -> Result<Quilt, String> {
    let b = config.block_px;
    let ov = config.overlap_px;
    if b == 0 || ov >= b {
        return Err(format!("block {b} px with overlap {ov} px is degenerate"));
    }
    if source.width < b || source.height < b {
        return Err(format!(
            "is {}×{}, smaller than a block of {b} px",
            source.width, source.height
        ));
    }
    let step = b - ov;
    let count = |side: usize| side.saturating_sub(ov).div_ceil(step).max(1);
    let (nx, ny) = (count(config.width), count(config.height));
    let (cw, chh) = (nx * step + ov, ny * step + ov);
    let c = source.channels;
    let mut canvas = Texture::zeros(cw, chh, c);
    let mut rng = SplitMix64::new(config.seed);
    let (mut overlap_sum, mut overlap_samples) = (0.0f64, 0usize);
    let (mut seam_sum, mut seam_pixels) = (0.0f64, 0usize);
    let mut sources = Vec::with_capacity(nx * ny);
    let (sw, sh) = (source.width - b + 1, source.height - b + 1);
    for by in 0..ny {
        for bx in 0..nx {
            let (px, py) = (bx * step, by * step);
            let left = bx > 0 && ov > 0;
            let top = by > 0 && ov > 0;
            // The overlap, row by row: whole rows in the top strip, the first `ov` columns
            // below it (only the left strip).
            let row_span = |y: usize| {
                if top && y < ov {
                    b
                } else if left {
                    ov
                } else {
                    0
                }
            };
            let errors: Vec<f64> = (0..sh)
                .into_par_iter()
                .flat_map_iter(|sy| {
                    let canvas = &canvas;
                    (0..sw).map(move |sx| {
                        if !left && !top {
                            return 0.0;
                        }
                        let mut ssd = 0.0f64;
                        for y in 0..b {
                            for x in 0..row_span(y) {
                                ssd += pixel_ssd(
                                    canvas.pixel(px + x, py + y),
                                    source.pixel(sx + x, sy + y),
                                );
                            }
                        }
                        ssd
                    })
                })
                .collect();
            let chosen = choose_within(&errors, config.tolerance, &mut rng);
            let (sx, sy) = (chosen % sw, chosen / sw);
            sources.push((sx, sy));
            if left || top {
                let samples = ((if left { ov * b } else { 0 }) + (if top { ov * b } else { 0 })
                    - (if left && top { ov * ov } else { 0 }))
                    * c;
                overlap_sum += errors[chosen] / samples as f64;
                overlap_samples += 1;
            }
            // Squared difference between the old and the new block, per block pixel.
            let diff = |x: usize, y: usize| {
                pixel_ssd(canvas.pixel(px + x, py + y), source.pixel(sx + x, sy + y))
            };
            // The cut through an overlap strip of `b` rows of `ov` samples; `at(row, k)` is the
            // block pixel of sample k of that row (the top strip is read transposed).
            let cut = |at: &dyn Fn(usize, usize) -> (usize, usize)| -> Vec<usize> {
                if !config.boundary_cut {
                    return vec![0; b];
                }
                let costs: Vec<f64> = (0..b)
                    .flat_map(|row| (0..ov).map(move |k| (row, k)))
                    .map(|(row, k)| {
                        let (x, y) = at(row, k);
                        diff(x, y)
                    })
                    .collect();
                min_cut_path(&costs, b, ov).0
            };
            let mut take_new = vec![true; b * b];
            let mut seam = Vec::new();
            if left {
                for (y, cut) in cut(&|y, x| (x, y)).into_iter().enumerate() {
                    take_new[y * b..y * b + cut].fill(false);
                    seam.push((cut, y));
                }
            }
            if top {
                for (x, cut) in cut(&|x, y| (x, y)).into_iter().enumerate() {
                    for y in 0..cut {
                        take_new[y * b + x] = false;
                    }
                    seam.push((x, cut));
                }
            }
            // A pixel on both cuts of an L-shaped overlap counts once.
            seam.sort_unstable_by_key(|&(x, y)| (y, x));
            seam.dedup();
            for &(x, y) in &seam {
                if take_new[y * b + x] {
                    seam_sum += diff(x, y) / c as f64;
                    seam_pixels += 1;
                }
            }
            for y in 0..b {
                for x in 0..b {
                    if take_new[y * b + x] {
                        canvas
                            .pixel_mut(px + x, py + y)
                            .copy_from_slice(source.pixel(sx + x, sy + y));
                    }
                }
            }
        }
    }
    let mut texture = Texture::zeros(config.width, config.height, c);
    for y in 0..config.height {
        let row = config.width * c;
        texture.samples[y * row..(y + 1) * row]
            .copy_from_slice(&canvas.samples[y * cw * c..][..row]);
    }
    let rms = |sum: f64, n: usize| if n == 0 { 0.0 } else { (sum / n as f64).sqrt() };
    Ok(Quilt {
        texture,
        blocks: nx * ny,
        overlap_rms: rms(overlap_sum, overlap_samples),
        seam_rms: rms(seam_sum, seam_pixels),
        sources,
    })
}

/// Σ over channels of the squared difference of two pixels, f64.
pub(crate) fn pixel_ssd(a: &[f32], b: &[f32]) -> f64 {
    a.iter().zip(b).map(|(x, y)| f64::from(x - y).powi(2)).sum()
}

/// Index drawn uniformly among the `errors` ≤ (1 + tolerance) · their minimum (in index
/// order, so the draw is reproducible). `errors` must not be empty.
pub(crate) fn choose_within(errors: &[f64], tolerance: f64, rng: &mut SplitMix64) -> usize {
    let best = errors.iter().copied().fold(f64::INFINITY, f64::min);
    let limit = best * (1.0 + tolerance);
    let candidates: Vec<usize> = (0..errors.len()).filter(|&i| errors[i] <= limit).collect();
    let pick = ((rng.uniform() * candidates.len() as f64) as usize).min(candidates.len() - 1);
    candidates[pick]
}

/// Minimum-cost top-to-bottom path through a `rows × cols` cost matrix (row-major), moving
/// at most one column between consecutive rows: the column of the path in every row, and its
/// total cost. Dynamic programming E(i, j) = e(i, j) + min(E(i−1, j−1..=j+1)); ties go to the
/// smallest column. Empty input gives an empty path of cost 0.
pub fn min_cut_path(costs: &[f64], rows: usize, cols: usize) -> (Vec<usize>, f64) {
    if rows == 0 || cols == 0 || costs.len() != rows * cols {
        return (Vec::new(), 0.0);
    }
    let mut total = costs[..cols].to_vec();
    let mut from = vec![0usize; rows * cols];
    for i in 1..rows {
        let prev = total.clone();
        for j in 0..cols {
            let lo = j.saturating_sub(1);
            let hi = (j + 1).min(cols - 1);
            let best = (lo..=hi).fold(lo, |b, k| if prev[k] < prev[b] { k } else { b });
            from[i * cols + j] = best;
            total[j] = prev[best] + costs[i * cols + j];
        }
    }
    let end = (1..cols).fold(0, |e, j| if total[j] < total[e] { j } else { e });
    let cost = total[end];
    let mut path = vec![0; rows];
    path[rows - 1] = end;
    for i in (1..rows).rev() {
        path[i - 1] = from[i * cols + path[i]];
    }
    (path, cost)
}

#[cfg(test)]
mod tests {
    use super::super::test_support::{blobs, noise, periodic};
    use super::super::{channel_moments, patch_match_rms};
    use super::*;
    use proptest::prelude::*;

    fn config(width: usize, height: usize, block_px: usize, overlap_px: usize) -> QuiltConfig {
        QuiltConfig {
            width,
            height,
            block_px,
            overlap_px,
            tolerance: 0.1,
            boundary_cut: true,
            seed: 3,
        }
    }

    /// Every path (one column per row, steps of at most one column) and the cheapest cost.
    fn brute_force(costs: &[f64], rows: usize, cols: usize) -> f64 {
        fn go(costs: &[f64], rows: usize, cols: usize, i: usize, j: usize) -> f64 {
            let here = costs[i * cols + j];
            if i + 1 == rows {
                return here;
            }
            let lo = j.saturating_sub(1);
            let hi = (j + 1).min(cols - 1);
            here + (lo..=hi)
                .map(|k| go(costs, rows, cols, i + 1, k))
                .fold(f64::INFINITY, f64::min)
        }
        (0..cols)
            .map(|j| go(costs, rows, cols, 0, j))
            .fold(f64::INFINITY, f64::min)
    }

    #[test]
    fn hand_made_cut_follows_the_cheap_valley() {
        #[rustfmt::skip]
        let costs = [
            9.0, 1.0, 9.0,
            9.0, 9.0, 1.0,
            9.0, 1.0, 9.0,
            1.0, 9.0, 9.0,
        ];
        let (path, cost) = min_cut_path(&costs, 4, 3);
        assert_eq!(path, vec![1, 2, 1, 0]);
        assert_eq!(cost, 4.0);
    }

    proptest! {
        /// The DP path is valid, costs what it says, and is as cheap as the brute-force best.
        #[test]
        fn cut_matches_brute_force(rows in 1usize..7, cols in 1usize..5, seed in 0u64..10_000) {
            let mut rng = SplitMix64::new(seed);
            let costs: Vec<f64> = (0..rows * cols).map(|_| (rng.uniform() * 10.0).floor()).collect();
            let (path, cost) = min_cut_path(&costs, rows, cols);
            prop_assert_eq!(path.len(), rows);
            for w in path.windows(2) {
                prop_assert!(w[0].abs_diff(w[1]) <= 1);
            }
            let along: f64 = path.iter().enumerate().map(|(i, &j)| costs[i * cols + j]).sum();
            prop_assert_eq!(along, cost);
            prop_assert_eq!(cost, brute_force(&costs, rows, cols));
        }
    }

    #[test]
    fn periodic_texture_with_block_of_one_period_is_reproduced() {
        let period = 8;
        let source = periodic(40, 40, period, 11);
        let result = quilt(&source, &config(50, 44, period, 3)).unwrap();
        assert_eq!(result.overlap_rms, 0.0);
        assert_eq!(result.seam_rms, 0.0);
        let out = &result.texture;
        // The output is the source's tile, shifted by the first block's phase.
        let (sx, sy) = result.sources[0];
        for y in 0..out.height {
            for x in 0..out.width {
                assert_eq!(
                    out.pixel(x, y),
                    source.pixel((x + sx) % period, (y + sy) % period)
                );
            }
        }
    }

    #[test]
    fn output_looks_like_the_source() {
        let source = blobs(48, 48, 5);
        let result = quilt(&source, &config(80, 72, 16, 4)).unwrap();
        let out = &result.texture;
        assert_eq!((out.width, out.height), (80, 72));
        let (sm, sv) = channel_moments(&source)[0];
        let (om, ov) = channel_moments(out)[0];
        assert!((sm - om).abs() < 0.25 * sv.sqrt(), "means {sm} {om}");
        // Quilting favours blocks that match smoothly, which lowers the variance somewhat.
        assert!((ov / sv - 1.0).abs() < 0.5, "variances {sv} {ov}");
        // Output neighbourhoods are close to source neighbourhoods; independent noise is not.
        let rms = patch_match_rms(out, &source, 7, 5).unwrap();
        let baseline = patch_match_rms(&noise(80, 72, 1), &source, 7, 5).unwrap();
        assert!(rms < 0.25 * baseline, "{rms} vs noise {baseline}");
    }

    #[test]
    fn cut_lowers_the_seam_error() {
        let source = blobs(48, 48, 9);
        let with_cut = quilt(&source, &config(72, 72, 16, 6)).unwrap();
        let straight = quilt(
            &source,
            &QuiltConfig {
                boundary_cut: false,
                ..config(72, 72, 16, 6)
            },
        )
        .unwrap();
        assert!(
            with_cut.seam_rms < straight.seam_rms,
            "{} vs {}",
            with_cut.seam_rms,
            straight.seam_rms
        );
    }

    #[test]
    fn same_result_for_one_and_many_threads() {
        let source = blobs(40, 40, 2);
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| quilt(&source, &config(64, 64, 12, 3)).unwrap())
        };
        assert_eq!(run(1), run(4));
    }

    #[test]
    fn bad_inputs_are_rejected() {
        let small = blobs(10, 10, 1);
        assert!(quilt(&small, &config(32, 32, 16, 4)).is_err());
        assert!(
            Quilting::new(QuiltingParams {
                overlap_px: 8,
                block_px: 8,
                ..Default::default()
            })
            .is_err()
        );
        assert!(
            Quilting::new(QuiltingParams {
                tolerance: f64::NAN,
                ..Default::default()
            })
            .is_err()
        );
        assert!(
            Quilting::new(QuiltingParams {
                width: 0,
                ..Default::default()
            })
            .is_err()
        );
    }
}
