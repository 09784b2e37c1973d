//! `video.block_match`: block-matching motion vectors (SAD cost), full search or three-step
//! coarse-to-fine search, with optional half-pixel refinement.
//!
//! [`block_match`] cuts `previous` into `block_px` squares and finds, for each, the displacement
//! within `±search_px` that minimises the sum of absolute differences against `next`.
//!
//! How it runs: block rows are processed in parallel, one block row per task; each block's
//! search is sequential in a fixed order, so the vectors are bit-identical for any thread
//! count.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Matrix, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::gray::{Plane, gray_f32};

/// Largest block side, px.
pub const MAX_BLOCK: u32 = 256;

/// Largest search radius, px.
pub const MAX_SEARCH: u32 = 256;

param_enum! {
    /// Search strategy of `video.block_match`.
    pub enum SearchMethod {
        /// Every integer displacement in the `±search_px` square (exhaustive; finds the global
        /// SAD minimum).
        Full = "full",
        /// Three-step search (Koga et al. 1981): the 3×3 pattern of displacements at a step of
        /// about `search_px / 2`, recentred on the best one, with the step halved down to 1 px.
        /// Far fewer evaluations; can stop in a local minimum.
        CoarseToFine = "coarse_to_fine",
    }
}

params! {
    /// Parameters of `video.block_match`.
    pub struct BlockMatchParams {
        /// Side of the square blocks, px, 1..=256. Blocks tile the image from its top-left
        /// corner; a partial block at the right or bottom edge is not matched. Default 16.
        block_px: u32 = 16,
        /// Largest displacement searched along each axis, px, 0..=256. Default 16.
        search_px: u32 = 16,
        /// Search strategy: "full" or "coarse_to_fine". Default "full".
        method: SearchMethod = SearchMethod::Full,
        /// Refine the best integer vector over its 8 half-pixel neighbours (next frame sampled
        /// bilinearly). Default true.
        half_pixel: bool = true,
    }
}

/// One block's motion vector.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlockVector {
    /// Block centre column in `previous`, px.
    pub x: f32,
    /// Block centre row, px.
    pub y: f32,
    /// Displacement of the block's content from `previous` to `next`, px.
    pub dx: f32,
    /// Vertical displacement, px.
    pub dy: f32,
    /// SAD at the displacement (0–255 gray scale, summed over the block).
    pub cost: f32,
}

/// Block matching (`video.block_match`). See [`block_match`].
#[derive(Debug, Clone, PartialEq)]
pub struct BlockMatch {
    block: usize,
    search: usize,
    method: SearchMethod,
    half_pixel: bool,
}

impl Op for BlockMatch {
    type Params = BlockMatchParams;
    const ID: &'static str = "video.block_match";
    const SUMMARY: &'static str = "Estimates one motion vector per image block by minimising the sum of absolute differences.";
    const DOC: &'static str = r#"
Cuts `previous` into `block_px` × `block_px` blocks (from the top-left corner; partial edge
blocks are skipped) and finds for each the displacement `(dx, dy)`, `|dx|, |dy| ≤ search_px`,
whose block in `next` has the smallest sum of absolute differences (SAD) with it. Frames are
converted to gray f32 on the 0–255 scale (u16 / 257, f32 · 255, RGB by BT.601 luma).
Candidates whose block would leave `next` are not considered; ties keep the earlier candidate
(zero motion first, then raster order).

`method: "full"` tries every integer displacement; `"coarse_to_fine"` is the three-step search
(3×3 pattern, step halved each round). With `half_pixel` the best integer vector is refined over
its 8 half-pixel neighbours, `next` sampled bilinearly (the MPEG-style half-pel search).

Outputs: `vectors`, a Matrix with one row `[x, y, dx, dy, cost]` per block in raster order
(x, y the block centre in px, cost the SAD); `u` and `v`, gray f32 images with one pixel per
block holding dx and dy.

Reference: J. R. Jain, A. K. Jain, "Displacement measurement and its application in
interframe image coding", IEEE Trans. Commun. 1981; T. Koga et al., "Motion-compensated
interframe coding for video conferencing", NTC 1981 (three-step search). OpenCV has no
direct equivalent (its legacy `cvCalcOpticalFlowBM` was removed).

Example:
    "motion": (op: "video.block_match", inputs: { "previous": "a.image", "next": "b.image" }, params: (block_px: 16, search_px: 16)),
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
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "vectors",
                PortType::Matrix,
                "One row [x, y, dx, dy, cost] per block, raster order.",
            ),
            PortSpec::new("u", PortType::Image, "dx per block, gray f32, px."),
            PortSpec::new("v", PortType::Image, "dy per block, gray f32, px."),
        ]
    }

    fn new(params: BlockMatchParams) -> Result<Self, String> {
        let BlockMatchParams {
            block_px,
            search_px,
            method,
            half_pixel,
        } = params;
        if !(1..=MAX_BLOCK).contains(&block_px) {
            return Err(format!(
                "`block_px` must be between 1 and {MAX_BLOCK}, got {block_px}"
            ));
        }
        if search_px > MAX_SEARCH {
            return Err(format!(
                "`search_px` must be at most {MAX_SEARCH}, got {search_px}"
            ));
        }
        Ok(BlockMatch {
            block: block_px as usize,
            search: search_px as usize,
            method,
            half_pixel,
        })
    }
}

impl Operator for BlockMatch {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let previous = inputs.image("previous")?;
        let next = inputs.image("next")?;
        let field = block_match(
            previous,
            next,
            self.block,
            self.search,
            self.method,
            self.half_pixel,
        )
        .map_err(OpError::failed)?;
        let data = field
            .vectors
            .iter()
            .flat_map(|b| [b.x, b.y, b.dx, b.dy, b.cost].map(f64::from))
            .collect();
        let matrix = Matrix::new(field.vectors.len(), 5, data)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let image = |f: fn(&BlockVector) -> f32| {
            Image::from_f32(
                field.columns,
                field.rows,
                Channels::Gray,
                field.vectors.iter().map(f).collect(),
            )
            .map_err(|e| OpError::failed(e.to_string()))
        };
        Ok(Outputs::new()
            .with("vectors", Value::Matrix(Arc::new(matrix)))
            .with("u", Value::image(image(|b| b.dx)?))
            .with("v", Value::image(image(|b| b.dy)?)))
    }
}

/// The vector field of [`block_match`].
#[derive(Debug, Clone, PartialEq)]
pub struct BlockField {
    /// Blocks per row.
    pub columns: usize,
    /// Block rows.
    pub rows: usize,
    /// `columns × rows` vectors, raster order.
    pub vectors: Vec<BlockVector>,
}

/// Block-matching motion vectors from `previous` to `next` (same size, any pixel format):
/// `block`-px blocks, displacements up to `search` px, SAD cost. See [`BlockMatchParams`].
pub fn block_match(
    previous: &Image,
    next: &Image,
    block: usize,
    search: usize,
    method: SearchMethod,
    half_pixel: bool,
) -> Result<BlockField, String> {
    if previous.width() != next.width() || previous.height() != next.height() {
        return Err(format!(
            "`previous` is {}×{} but `next` is {}×{}",
            previous.width(),
            previous.height(),
            next.width(),
            next.height()
        ));
    }
    let block = block.max(1);
    let a = gray_f32(previous);
    let b = gray_f32(next);
    let columns = a.width / block;
    let rows = a.height / block;
    let mut vectors = vec![
        BlockVector {
            x: 0.0,
            y: 0.0,
            dx: 0.0,
            dy: 0.0,
            cost: 0.0
        };
        columns * rows
    ];
    if columns == 0 {
        return Ok(BlockField {
            columns,
            rows,
            vectors,
        });
    }
    vectors
        .par_chunks_mut(columns)
        .enumerate()
        .for_each(|(by, row)| {
            for (bx, out) in row.iter_mut().enumerate() {
                *out = match_block(
                    &a,
                    &b,
                    bx * block,
                    by * block,
                    block,
                    search,
                    method,
                    half_pixel,
                );
            }
        });
    Ok(BlockField {
        columns,
        rows,
        vectors,
    })
}

/// SAD of the block of `a` at (x0, y0) against `b` at integer offset (dx, dy); `None` when the
/// displaced block leaves `b`.
#[inline]
fn sad(a: &Plane, b: &Plane, x0: usize, y0: usize, n: usize, dx: i64, dy: i64) -> Option<f32> {
    let bx = x0 as i64 + dx;
    let by = y0 as i64 + dy;
    if bx < 0 || by < 0 || bx as usize + n > b.width || by as usize + n > b.height {
        return None;
    }
    let (bx, by) = (bx as usize, by as usize);
    let mut total = 0.0f32;
    for r in 0..n {
        let ra = &a.data[(y0 + r) * a.width + x0..][..n];
        let rb = &b.data[(by + r) * b.width + bx..][..n];
        let mut s = 0.0f32;
        for (p, q) in ra.iter().zip(rb) {
            s += (p - q).abs();
        }
        total += s;
    }
    Some(total)
}

/// SAD against `b` displaced by the half-pixel offset (hx, hy)/2, `b` sampled bilinearly.
fn sad_half(a: &Plane, b: &Plane, x0: usize, y0: usize, n: usize, hx: i64, hy: i64) -> Option<f32> {
    let fx = hx.rem_euclid(2) as f32 * 0.5;
    let fy = hy.rem_euclid(2) as f32 * 0.5;
    let bx = x0 as i64 + hx.div_euclid(2);
    let by = y0 as i64 + hy.div_euclid(2);
    let ex = usize::from(fx > 0.0);
    let ey = usize::from(fy > 0.0);
    if bx < 0 || by < 0 || bx as usize + n + ex > b.width || by as usize + n + ey > b.height {
        return None;
    }
    let (bx, by) = (bx as usize, by as usize);
    let mut total = 0.0f32;
    for r in 0..n {
        let ra = &a.data[(y0 + r) * a.width + x0..][..n];
        let r0 = &b.data[(by + r) * b.width + bx..][..n + ex];
        let r1 = &b.data[(by + r + ey) * b.width + bx..][..n + ex];
        let mut s = 0.0f32;
        for c in 0..n {
            let top = r0[c] + (r0[c + ex] - r0[c]) * fx;
            let bottom = r1[c] + (r1[c + ex] - r1[c]) * fx;
            s += (ra[c] - (top + (bottom - top) * fy)).abs();
        }
        total += s;
    }
    Some(total)
}

/// The motion vector of the `n × n` block of `a` at (x0, y0) into `b`: the displacement
/// `(dx, dy)` (`|dx|, |dy| ≤ search`) whose block of `b` at `(x0 + dx, y0 + dy)` has the least
/// SAD, found by `method`, optionally refined to half pixels. Candidates leaving `b` are skipped.
#[allow(clippy::too_many_arguments)]
pub(crate) fn match_block(
    a: &Plane,
    b: &Plane,
    x0: usize,
    y0: usize,
    n: usize,
    search: usize,
    method: SearchMethod,
    half_pixel: bool,
) -> BlockVector {
    let s = search as i64;
    let mut best = (0i64, 0i64);
    let mut best_cost = sad(a, b, x0, y0, n, 0, 0).unwrap_or(f32::INFINITY);
    let consider = |dx: i64, dy: i64, best: &mut (i64, i64), best_cost: &mut f32| {
        if let Some(c) = sad(a, b, x0, y0, n, dx, dy)
            && c < *best_cost
        {
            *best_cost = c;
            *best = (dx, dy);
        }
    };
    match method {
        SearchMethod::Full => {
            for dy in -s..=s {
                for dx in -s..=s {
                    consider(dx, dy, &mut best, &mut best_cost);
                }
            }
        }
        SearchMethod::CoarseToFine => {
            let mut step = (search as u64).div_ceil(2).next_power_of_two() as i64;
            if search == 0 {
                step = 0;
            }
            while step >= 1 {
                let centre = best;
                for j in -1..=1 {
                    for i in -1..=1 {
                        let (dx, dy) = (centre.0 + i * step, centre.1 + j * step);
                        if dx.abs() <= s && dy.abs() <= s {
                            consider(dx, dy, &mut best, &mut best_cost);
                        }
                    }
                }
                step /= 2;
            }
        }
    }
    let (mut dx, mut dy) = (best.0 as f32, best.1 as f32);
    if half_pixel && best_cost.is_finite() {
        let centre = (2 * best.0, 2 * best.1);
        let mut half_best = centre;
        for j in -1..=1 {
            for i in -1..=1 {
                if i == 0 && j == 0 {
                    continue;
                }
                let (hx, hy) = (centre.0 + i, centre.1 + j);
                if let Some(c) = sad_half(a, b, x0, y0, n, hx, hy)
                    && c < best_cost
                {
                    best_cost = c;
                    half_best = (hx, hy);
                }
            }
        }
        dx = half_best.0 as f32 * 0.5;
        dy = half_best.1 as f32 * 0.5;
    }
    let centre = (n as f32 - 1.0) * 0.5;
    BlockVector {
        x: x0 as f32 + centre,
        y: y0 as f32 + centre,
        dx,
        dy,
        cost: if best_cost.is_finite() {
            best_cost
        } else {
            f32::NAN
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::video::synth::blob_texture;
    use ocellus_engine::value::PixelData;

    const IDENTITY: [f64; 6] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0];

    fn samples(image: &Image) -> Vec<f32> {
        match image.data() {
            PixelData::F32(v) => v.clone(),
            _ => panic!(),
        }
    }

    /// `next(x, y) = prev(x − sx, y − sy)` for a half-integer shift, as bilinear averages of
    /// `prev` (edge pixels replicated).
    fn shifted(prev: &Image, sx2: i64, sy2: i64) -> Image {
        let (w, h) = (prev.width() as i64, prev.height() as i64);
        let p = samples(prev);
        let at = |x: i64, y: i64| p[(y.clamp(0, h - 1) * w + x.clamp(0, w - 1)) as usize];
        let mut out = Vec::new();
        for y in 0..h {
            for x in 0..w {
                // Source position (2x − sx2)/2: floor and a half-pixel fraction.
                let (ux, uy) = (2 * x - sx2, 2 * y - sy2);
                let (x0, y0) = (ux.div_euclid(2), uy.div_euclid(2));
                let (fx, fy) = (ux.rem_euclid(2) as f32 * 0.5, uy.rem_euclid(2) as f32 * 0.5);
                let top = at(x0, y0) + (at(x0 + 1, y0) - at(x0, y0)) * fx;
                let bottom = at(x0, y0 + 1) + (at(x0 + 1, y0 + 1) - at(x0, y0 + 1)) * fx;
                out.push(top + (bottom - top) * fy);
            }
        }
        Image::from_f32(prev.width(), prev.height(), Channels::Gray, out).unwrap()
    }

    /// Vectors of blocks whose search window stays inside the image.
    fn interior(
        f: &BlockField,
        w: usize,
        h: usize,
        block: usize,
        search: usize,
    ) -> Vec<BlockVector> {
        let m = (search + 1) as f32;
        f.vectors
            .iter()
            .copied()
            .filter(|v| {
                let half = block as f32 / 2.0;
                v.x - half >= m
                    && v.y - half >= m
                    && v.x + half + m <= w as f32
                    && v.y + half + m <= h as f32
            })
            .collect()
    }

    #[test]
    fn integer_shift_recovered_exactly_by_both_methods() {
        let a = blob_texture(128, 96, 2.5, 3, IDENTITY).unwrap();
        let b = blob_texture(128, 96, 2.5, 3, [1.0, 0.0, -5.0, 0.0, 1.0, 3.0]).unwrap();
        for method in [SearchMethod::Full, SearchMethod::CoarseToFine] {
            let f = block_match(&a, &b, 16, 8, method, true).unwrap();
            assert_eq!((f.columns, f.rows), (8, 6));
            let inner = interior(&f, 128, 96, 16, 8);
            assert!(!inner.is_empty());
            for v in inner {
                assert_eq!(
                    (v.dx, v.dy),
                    (5.0, -3.0),
                    "{method:?} at ({}, {})",
                    v.x,
                    v.y
                );
                assert!(v.cost < 1e-3);
            }
        }
    }

    #[test]
    fn half_pixel_shift_recovered_exactly() {
        // `previous` is `next` resampled half a pixel off (bilinear), so the block of
        // `previous` is exactly `next` sampled at the half-pixel displacement.
        let b = blob_texture(96, 96, 2.5, 4, IDENTITY).unwrap();
        for (sx2, sy2) in [(3i64, -5i64), (-4, 1), (7, 7)] {
            let a = shifted(&b, -sx2, -sy2);
            let f = block_match(&a, &b, 16, 6, SearchMethod::Full, true).unwrap();
            for v in interior(&f, 96, 96, 16, 6) {
                assert_eq!((v.dx, v.dy), (sx2 as f32 / 2.0, sy2 as f32 / 2.0));
                assert!(v.cost < 1e-2, "cost {}", v.cost);
            }
            // Without refinement the vector is within half a pixel.
            let f = block_match(&a, &b, 16, 6, SearchMethod::Full, false).unwrap();
            for v in interior(&f, 96, 96, 16, 6) {
                assert!((v.dx - sx2 as f32 / 2.0).abs() <= 0.5 && v.dx.fract() == 0.0);
            }
        }
    }

    #[test]
    fn full_search_finds_the_global_minimum() {
        // Brute-force check of the SAD minimum on a random pair.
        let a = crate::filter::test_support::random_u8(40, 40, Channels::Gray, 1);
        let b = crate::filter::test_support::random_u8(40, 40, Channels::Gray, 2);
        let f = block_match(&a, &b, 8, 3, SearchMethod::Full, false).unwrap();
        let (pa, pb) = (gray_f32(&a), gray_f32(&b));
        for (k, v) in f.vectors.iter().enumerate() {
            let (x0, y0) = ((k % 5) * 8, (k / 5) * 8);
            let mut best = f32::INFINITY;
            for dy in -3..=3 {
                for dx in -3..=3 {
                    if let Some(c) = sad(&pa, &pb, x0, y0, 8, dx, dy) {
                        best = best.min(c);
                    }
                }
            }
            assert_eq!(v.cost, best);
        }
    }

    #[test]
    fn extremes_and_determinism() {
        let flat = Image::from_u8(32, 32, Channels::Gray, vec![9; 1024]).unwrap();
        let f = block_match(&flat, &flat, 8, 4, SearchMethod::Full, true).unwrap();
        assert!(
            f.vectors
                .iter()
                .all(|v| v.dx == 0.0 && v.dy == 0.0 && v.cost == 0.0)
        );
        let one = Image::from_u16(1, 1, Channels::Gray, vec![7]).unwrap();
        let f = block_match(&one, &one, 16, 4, SearchMethod::Full, true).unwrap();
        assert!(f.vectors.is_empty());
        let f = block_match(&one, &one, 1, 4, SearchMethod::CoarseToFine, true).unwrap();
        assert_eq!(f.vectors.len(), 1);
        assert!(!f.vectors[0].cost.is_nan());
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        assert!(
            block_match(&empty, &empty, 8, 4, SearchMethod::Full, true)
                .unwrap()
                .vectors
                .is_empty()
        );
        assert!(block_match(&flat, &one, 8, 4, SearchMethod::Full, true).is_err());
        let a = crate::filter::test_support::random_u8(64, 48, Channels::Rgb, 5);
        let b = crate::filter::test_support::random_u8(64, 48, Channels::Rgb, 6);
        let runs: Vec<BlockField> = [1, 4]
            .iter()
            .map(|&n| {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(n)
                    .build()
                    .unwrap();
                pool.install(|| block_match(&a, &b, 8, 5, SearchMethod::Full, true).unwrap())
            })
            .collect();
        assert_eq!(runs[0], runs[1]);
    }

    #[test]
    fn operator_outputs_and_bad_params() {
        assert!(
            BlockMatch::new(BlockMatchParams {
                block_px: 0,
                ..Default::default()
            })
            .is_err()
        );
        assert!(
            BlockMatch::new(BlockMatchParams {
                search_px: 300,
                ..Default::default()
            })
            .is_err()
        );
        let op = BlockMatch::new(BlockMatchParams::default()).unwrap();
        let a = blob_texture(64, 48, 2.5, 3, IDENTITY).unwrap();
        let b = blob_texture(64, 48, 2.5, 3, [1.0, 0.0, -1.0, 0.0, 1.0, 0.0]).unwrap();
        let specs = BlockMatch::inputs();
        let values = vec![Some(Value::image(a)), Some(Value::image(b))];
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
        let Some(Value::Matrix(m)) = out.take("vectors") else {
            panic!()
        };
        assert_eq!((m.rows, m.cols), (12, 5));
        assert_eq!(&m.data[..2], &[7.5, 7.5]);
        let Some(Value::Image(u)) = out.take("u") else {
            panic!()
        };
        assert_eq!((u.width(), u.height()), (4, 3));
    }
}
