//! `match.patch`: finds keypoints of a left image in a right image by patch comparison (SSD,
//! NCC or ZNCC) over a square search window, with a parabola fit for subpixel positions.
//!
//! Each keypoint is handled independently (in parallel over fixed chunks of keypoints), with
//! sums accumulated per patch row in f64 in a fixed order: results do not depend on the thread
//! count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Image, Keypoint, Match, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::keypoints;

/// Moves of the subpixel fit's centre towards a vertex more than half a pixel away.
const REFITS: usize = 2;

/// Keypoints per parallel task.
const CHUNK: usize = 16;

/// Largest patch side, px.
pub const MAX_WINDOW: u32 = 101;

/// Largest search radius, px.
pub const MAX_RADIUS: u32 = 512;

param_enum! {
    /// Patch comparison score.
    pub enum Score {
        /// Mean squared difference (cost, lower is better; in squared image units).
        Ssd = "ssd",
        /// Normalized cross-correlation Σab / √(Σa² Σb²) (invariant to gain).
        Ncc = "ncc",
        /// Zero-mean normalized cross-correlation (invariant to gain and offset).
        Zncc = "zncc",
    }
}

params! {
    /// Parameters of `match.patch`.
    pub struct PatchParams {
        /// Comparison: "ssd", "ncc" or "zncc". Default "zncc".
        score: Score = Score::Zncc,
        /// Patch side, px (odd, 1–101). Default 11.
        window_px: u32 = 11 => [min = 1, max = 101, unit = "px"],
        /// The right patch centre is searched over integer offsets in [−r, r]² around the
        /// keypoint's position, px. Default 16.
        search_radius_px: u32 = 16 => [max = 512, unit = "px"],
        /// Refine the best offset to subpixel precision with a quadratic surface through the
        /// 3×3 costs around it. Default true.
        subpixel: bool = true,
        /// Drop matches whose cost exceeds this: mean squared difference for "ssd",
        /// 1 − correlation (0–2) for "ncc" and "zncc". Default none.
        max_cost: Option<f64> = None => [min = 0.0],
    }
}

/// Patch matcher (`match.patch`). See [`match_patches`].
#[derive(Debug, Clone, PartialEq)]
pub struct PatchMatch {
    options: PatchOptions,
}

/// Options of [`match_patches`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PatchOptions {
    /// Comparison.
    pub score: Score,
    /// Half the (odd) patch side, px.
    pub half: usize,
    /// Search radius, px.
    pub radius: usize,
    /// Parabola refinement.
    pub subpixel: bool,
    /// Largest cost kept.
    pub max_cost: Option<f64>,
}

impl Op for PatchMatch {
    type Params = PatchParams;
    const ID: &'static str = "match.patch";
    const SUMMARY: &'static str =
        "Finds left-image keypoints in a right image by SSD / NCC / ZNCC patch search.";
    const DOC: &'static str = r#"
For every keypoint of the left image, compares the `window_px × window_px` patch around its
nearest pixel with right-image patches centred at integer offsets in [−r, r]² (r =
`search_radius_px`) from the same position, and keeps the best: lowest mean squared difference
(`ssd`), or highest normalized cross-correlation (`ncc`: Σab / √(Σa² Σb²), invariant to gain) or
zero-mean normalized cross-correlation (`zncc`: invariant to gain and offset). With `subpixel`,
the best offset is refined by the minimum of the quadratic surface through the 3×3 costs
around it (one Newton step with central differences, which handles textures whose x and y
structure is coupled; where that surface is not convex, a parabola per axis through the costs
at −1, 0, +1). Where the vertex is more than half a pixel away, the fit is repeated around
that neighbour (at most twice); the final step is clamped to ±0.5 px per axis. The keypoint's fractional part is carried
over, so the right position is `x + dx` for a locally translated patch.

Costs (the matches' `distance`): SSD mean squared difference in the image's units squared, or
1 − correlation (0 best, 2 worst). Patches that leave either image are not compared, and a
left patch with no variation (zero norm, or zero variance for ZNCC) gives no match; so do
costs above `max_cost`. Images are read as gray (RGB/RGBA by BT.601 luma) in their own units
(u8 0–255, u16 0–65535, f32 as is); both must have the same sample type.

Outputs: `matches` with query = left keypoint index and train = index into the output
`keypoints`, which hold the matched right positions (other fields copied from the left).

Reference: the usual area-based matching of stereo and tracking (e.g. R. Szeliski, "Computer
Vision: Algorithms and Applications", §9.1 and §12.3); OpenCV's `matchTemplate` scores
TM_SQDIFF, TM_CCORR_NORMED, TM_CCOEFF_NORMED.

Example:
    "track": (op: "match.patch", inputs: { "left": "frame0.image", "right": "frame1.image",
              "keypoints": "corners.keypoints" }, params: (score: "zncc", window_px: 11)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("left", PortType::Image, "First image (any format)."),
            PortSpec::new(
                "right",
                PortType::Image,
                "Second image, same sample type as the left.",
            ),
            PortSpec::new(
                "keypoints",
                PortType::Keypoints,
                "Positions to find, in the left image.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "matches",
                PortType::Matches,
                "query = left keypoint, train = output keypoint, distance = cost.",
            ),
            PortSpec::new(
                "keypoints",
                PortType::Keypoints,
                "Matched positions in the right image, one per match.",
            ),
        ]
    }

    fn new(params: PatchParams) -> Result<Self, String> {
        let PatchParams {
            score,
            window_px,
            search_radius_px,
            subpixel,
            max_cost,
        } = params;
        if window_px % 2 == 0 || !(1..=MAX_WINDOW).contains(&window_px) {
            return Err(format!(
                "`window_px` must be odd and 1..={MAX_WINDOW}, got {window_px}"
            ));
        }
        if search_radius_px > MAX_RADIUS {
            return Err(format!(
                "`search_radius_px` must be ≤ {MAX_RADIUS}, got {search_radius_px}"
            ));
        }
        if let Some(c) = max_cost
            && !(c.is_finite() && c >= 0.0)
        {
            return Err(format!("`max_cost` must be finite and ≥ 0, got {c}"));
        }
        Ok(PatchMatch {
            options: PatchOptions {
                score,
                half: (window_px / 2) as usize,
                radius: search_radius_px as usize,
                subpixel,
                max_cost,
            },
        })
    }
}

impl Operator for PatchMatch {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let left = inputs.image("left")?;
        let right = inputs.image("right")?;
        let points = keypoints(inputs, "keypoints")?;
        if left.depth() != right.depth() {
            return Err(OpError::input(
                "right",
                format!(
                    "sample type {} differs from the left image's {}",
                    right.depth().name(),
                    left.depth().name()
                ),
            ));
        }
        let l = Plane::of(left);
        let r = Plane::of(right);
        let (matches, found) = match_patches(&l, &r, points, &self.options);
        Ok(Outputs::new()
            .with("matches", Value::Matches(matches.into()))
            .with("keypoints", Value::Keypoints(found.into())))
    }
}

/// A gray f32 plane.
#[derive(Debug, Clone, PartialEq)]
pub struct Plane {
    /// Width, px.
    pub width: usize,
    /// Height, px.
    pub height: usize,
    /// Row-major samples.
    pub data: Vec<f32>,
}

impl Plane {
    /// The gray plane of `image` in its own units (RGB/RGBA: BT.601 luma; NaN read as 0).
    pub fn of(image: &Image) -> Plane {
        let c = image.channels().count();
        let samples: Vec<f32> = match image.data() {
            PixelData::U8(v) => v.iter().map(|&s| f32::from(s)).collect(),
            PixelData::U16(v) => v.iter().map(|&s| f32::from(s)).collect(),
            PixelData::F32(v) => v
                .iter()
                .map(|&s| if s.is_finite() { s } else { 0.0 })
                .collect(),
        };
        let data = if c == 1 {
            samples
        } else {
            samples
                .chunks_exact(c)
                .map(|p| 0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2])
                .collect()
        };
        Plane {
            width: image.width(),
            height: image.height(),
            data,
        }
    }
}

/// Finds each keypoint of `left` in `right` (see the operator doc). Returns the matches and the
/// right keypoints they index.
pub fn match_patches(
    left: &Plane,
    right: &Plane,
    points: &[Keypoint],
    options: &PatchOptions,
) -> (Vec<Match>, Vec<Keypoint>) {
    let mut found: Vec<Option<(f32, f32, f64)>> = vec![None; points.len()];
    found
        .par_chunks_mut(CHUNK)
        .enumerate()
        .for_each(|(c, slots)| {
            let mut patch = Vec::new();
            for (i, slot) in slots.iter_mut().enumerate() {
                *slot = find_one(left, right, &points[c * CHUNK + i], options, &mut patch);
            }
        });
    let mut matches = Vec::new();
    let mut out = Vec::new();
    for (i, (f, kp)) in found.iter().zip(points).enumerate() {
        if let Some((x, y, cost)) = *f
            && options.max_cost.is_none_or(|m| cost <= m)
        {
            matches.push(Match {
                query: i as u32,
                train: out.len() as u32,
                distance: cost as f32,
            });
            out.push(Keypoint { x, y, ..*kp });
        }
    }
    (matches, out)
}

/// The left patch, normalized for the score: values (zero-mean for ZNCC) and their norm.
struct LeftPatch<'a> {
    values: &'a [f32],
    norm: f64,
}

/// Best right position of one keypoint: (x, y, cost).
fn find_one(
    left: &Plane,
    right: &Plane,
    kp: &Keypoint,
    o: &PatchOptions,
    buffer: &mut Vec<f32>,
) -> Option<(f32, f32, f64)> {
    if !(kp.x.is_finite() && kp.y.is_finite()) {
        return None;
    }
    let h = o.half as i64;
    let side = 2 * o.half + 1;
    let (cx, cy) = (kp.x.round() as i64, kp.y.round() as i64);
    let inside = |p: &Plane, x: i64, y: i64| {
        x - h >= 0 && y - h >= 0 && x + h < p.width as i64 && y + h < p.height as i64
    };
    if !inside(left, cx, cy) {
        return None;
    }
    buffer.clear();
    for row in 0..side {
        let y = (cy - h) as usize + row;
        let x0 = (cx - h) as usize;
        buffer.extend_from_slice(&left.data[y * left.width + x0..y * left.width + x0 + side]);
    }
    let n = (side * side) as f64;
    let norm = match o.score {
        Score::Ssd => 1.0,
        Score::Ncc => buffer.iter().map(|&v| f64::from(v) * f64::from(v)).sum(),
        Score::Zncc => {
            let mean = buffer.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
            buffer
                .iter_mut()
                .for_each(|v| *v = (f64::from(*v) - mean) as f32);
            buffer.iter().map(|&v| f64::from(v) * f64::from(v)).sum()
        }
    };
    if norm <= 0.0 {
        return None;
    }
    let patch = LeftPatch {
        values: buffer,
        norm,
    };
    let cost_at = |dx: i64, dy: i64| -> Option<f64> {
        let (x, y) = (cx + dx, cy + dy);
        if !inside(right, x, y) {
            return None;
        }
        cost(right, x - h, y - h, side, &patch, o.score)
    };
    let r = o.radius as i64;
    let mut best: Option<(f64, i64, i64)> = None;
    for dy in -r..=r {
        for dx in -r..=r {
            if let Some(c) = cost_at(dx, dy)
                && best.is_none_or(|(b, _, _)| c < b)
            {
                best = Some((c, dx, dy));
            }
        }
    }
    let (c0, dx, dy) = best?;
    let (mut sx, mut sy) = (0.0, 0.0);
    let (mut dx, mut dy) = (dx, dy);
    if o.subpixel {
        // Fit around the best offset; where the vertex lies more than half a pixel away, move
        // to that neighbour and fit again (at most `REFITS` moves), then clamp to ±0.5 px.
        for attempt in 0..=REFITS {
            let mut c = [[None; 3]; 3];
            for (j, row) in c.iter_mut().enumerate() {
                for (i, v) in row.iter_mut().enumerate() {
                    *v = cost_at(dx + i as i64 - 1, dy + j as i64 - 1);
                }
            }
            (sx, sy) = subpixel_offset(&c);
            let (mx, my) = (sx.round() as i64, sy.round() as i64);
            if (mx == 0 && my == 0) || attempt == REFITS || cost_at(dx + mx, dy + my).is_none() {
                break;
            }
            dx += mx;
            dy += my;
        }
        sx = sx.clamp(-0.5, 0.5);
        sy = sy.clamp(-0.5, 0.5);
    }
    let x = f64::from(kp.x) + dx as f64 + sx;
    let y = f64::from(kp.y) + dy as f64 + sy;
    Some((x as f32, y as f32, c0))
}

/// Subpixel offset of the minimum of the 3×3 costs `c[dy + 1][dx + 1]`: the Newton step
/// `−H⁻¹ g` of the quadratic surface through them (central differences) where it is convex,
/// otherwise a parabola per axis through the centre row and column (0 where that is not convex
/// or a neighbour is missing). Components are clamped to ±1 px.
pub fn subpixel_offset(c: &[[Option<f64>; 3]; 3]) -> (f64, f64) {
    let Some(c0) = c[1][1] else {
        return (0.0, 0.0);
    };
    let axis = |m: Option<f64>, p: Option<f64>| match (m, p) {
        (Some(m), Some(p)) if m - 2.0 * c0 + p > 0.0 => {
            (0.5 * (m - p) / (m - 2.0 * c0 + p)).clamp(-0.5, 0.5)
        }
        _ => 0.0,
    };
    let all: Option<Vec<f64>> = c.iter().flatten().copied().collect();
    if let Some(v) = all {
        let at = |i: usize, j: usize| v[j * 3 + i];
        let gx = 0.5 * (at(2, 1) - at(0, 1));
        let gy = 0.5 * (at(1, 2) - at(1, 0));
        let hxx = at(2, 1) - 2.0 * c0 + at(0, 1);
        let hyy = at(1, 2) - 2.0 * c0 + at(1, 0);
        let hxy = 0.25 * (at(2, 2) - at(2, 0) - at(0, 2) + at(0, 0));
        let det = hxx * hyy - hxy * hxy;
        if hxx > 0.0 && det > 0.0 {
            let sx = -(hyy * gx - hxy * gy) / det;
            let sy = -(hxx * gy - hxy * gx) / det;
            return (sx.clamp(-1.0, 1.0), sy.clamp(-1.0, 1.0));
        }
    }
    (axis(c[1][0], c[1][2]), axis(c[0][1], c[2][1]))
}

/// Cost of the right patch with top-left corner (x0, y0) against `patch`; `None` for an
/// undefined correlation (flat right patch).
fn cost(
    right: &Plane,
    x0: i64,
    y0: i64,
    side: usize,
    patch: &LeftPatch<'_>,
    score: Score,
) -> Option<f64> {
    let (x0, y0) = (x0 as usize, y0 as usize);
    let (mut sab, mut sb, mut sbb) = (0.0f64, 0.0f64, 0.0f64);
    for (row, a) in patch.values.chunks_exact(side).enumerate() {
        let start = (y0 + row) * right.width + x0;
        let b = &right.data[start..start + side];
        let (mut rab, mut rb, mut rbb) = (0.0f32, 0.0f32, 0.0f32);
        match score {
            Score::Ssd => {
                for (&p, &q) in a.iter().zip(b) {
                    let d = p - q;
                    rab += d * d;
                }
            }
            _ => {
                for (&p, &q) in a.iter().zip(b) {
                    rab += p * q;
                    rb += q;
                    rbb += q * q;
                }
            }
        }
        sab += f64::from(rab);
        sb += f64::from(rb);
        sbb += f64::from(rbb);
    }
    let n = (side * side) as f64;
    match score {
        Score::Ssd => Some(sab / n),
        Score::Ncc => (sbb > 0.0).then(|| 1.0 - sab / (patch.norm * sbb).sqrt()),
        Score::Zncc => {
            // Σ a (b − b̄) = Σ a b since Σ a = 0.
            let var = sbb - sb * sb / n;
            (var > 1e-12 * sbb.max(1e-30)).then(|| 1.0 - sab / (patch.norm * var).sqrt())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::value::Channels;

    /// A smooth texture: sum of sinusoids with incommensurate frequencies.
    fn texture(x: f64, y: f64) -> f64 {
        100.0
            + 30.0 * (0.31 * x + 0.17 * y).sin()
            + 25.0 * (0.23 * x - 0.29 * y + 1.0).sin()
            + 20.0 * (0.13 * x * 0.7 + 0.41 * y).cos()
            + 15.0 * (0.37 * x + 0.05 * y + 2.0).cos()
    }

    fn plane(w: usize, h: usize, gain: f64, offset: f64, shift: (f64, f64)) -> Plane {
        let mut data = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                data.push((gain * texture(x as f64 - shift.0, y as f64 - shift.1) + offset) as f32);
            }
        }
        Plane {
            width: w,
            height: h,
            data,
        }
    }

    fn kp(x: f32, y: f32) -> Keypoint {
        Keypoint {
            x,
            y,
            size: 7.0,
            angle: -1.0,
            response: 1.0,
            octave: 0,
        }
    }

    fn grid() -> Vec<Keypoint> {
        (0..5)
            .flat_map(|j| (0..5).map(move |i| kp(30.0 + 10.0 * i as f32, 30.0 + 10.0 * j as f32)))
            .collect()
    }

    fn options(score: Score) -> PatchOptions {
        PatchOptions {
            score,
            half: 7,
            radius: 6,
            subpixel: true,
            max_cost: None,
        }
    }

    #[test]
    fn recovers_subpixel_shift() {
        let shift = (2.3, -1.6);
        let left = plane(100, 100, 1.0, 0.0, (0.0, 0.0));
        for (score, gain, offset) in [
            (Score::Ssd, 1.0, 0.0),
            (Score::Ncc, 1.0, 0.0),
            (Score::Ncc, 1.7, 0.0),
            (Score::Zncc, 1.0, 0.0),
            (Score::Zncc, 1.7, -40.0),
        ] {
            let right = plane(100, 100, gain, offset, shift);
            let points = grid();
            let (m, found) = match_patches(&left, &right, &points, &options(score));
            assert_eq!(m.len(), points.len(), "{score:?}");
            for (mm, (p, f)) in m.iter().zip(points.iter().zip(&found)) {
                assert_eq!(mm.train as usize, mm.query as usize);
                let (ex, ey) = (
                    f64::from(f.x) - f64::from(p.x),
                    f64::from(f.y) - f64::from(p.y),
                );
                assert!(
                    (ex - shift.0).abs() < 0.1 && (ey - shift.1).abs() < 0.1,
                    "{score:?} gain {gain}: ({ex}, {ey})"
                );
            }
        }
    }

    #[test]
    fn quadratic_surface_vertex() {
        // c = (x − 0.3)² + 2 (y + 0.2)² + (x − 0.3)(y + 0.2): minimum at (0.3, −0.2).
        let f =
            |x: f64, y: f64| (x - 0.3).powi(2) + 2.0 * (y + 0.2).powi(2) + (x - 0.3) * (y + 0.2);
        let mut c = [[None; 3]; 3];
        for (j, row) in c.iter_mut().enumerate() {
            for (i, v) in row.iter_mut().enumerate() {
                *v = Some(f(i as f64 - 1.0, j as f64 - 1.0));
            }
        }
        let (sx, sy) = subpixel_offset(&c);
        assert!(
            (sx - 0.3).abs() < 1e-12 && (sy + 0.2).abs() < 1e-12,
            "{sx} {sy}"
        );
        // A missing corner falls back to per-axis parabolas (exact here without coupling).
        let g = |x: f64, y: f64| (x - 0.25).powi(2) + (y - 0.1).powi(2);
        for (j, row) in c.iter_mut().enumerate() {
            for (i, v) in row.iter_mut().enumerate() {
                *v = Some(g(i as f64 - 1.0, j as f64 - 1.0));
            }
        }
        c[0][0] = None;
        let (sx, sy) = subpixel_offset(&c);
        assert!((sx - 0.25).abs() < 1e-12 && (sy - 0.1).abs() < 1e-12);
    }

    #[test]
    fn zncc_invariant_to_gain_and_offset() {
        let left = plane(90, 90, 1.0, 0.0, (0.0, 0.0));
        let a = plane(90, 90, 1.0, 0.0, (1.4, 0.8));
        let b = plane(90, 90, 2.0, 10.0, (1.4, 0.8));
        let (ma, fa) = match_patches(&left, &a, &grid(), &options(Score::Zncc));
        let (mb, fb) = match_patches(&left, &b, &grid(), &options(Score::Zncc));
        assert_eq!(ma.len(), mb.len());
        for ((x, y), (p, q)) in ma.iter().zip(&fa).zip(mb.iter().zip(&fb)) {
            assert!((x.distance - p.distance).abs() < 1e-5);
            assert!((y.x - q.x).abs() < 1e-3 && (y.y - q.y).abs() < 1e-3);
        }
    }

    #[test]
    fn integer_shift_is_exact_with_ssd() {
        let left = plane(80, 80, 1.0, 0.0, (0.0, 0.0));
        let right = plane(80, 80, 1.0, 0.0, (3.0, -2.0));
        let points = vec![kp(40.4, 40.0)];
        let mut o = options(Score::Ssd);
        o.subpixel = false;
        let (m, f) = match_patches(&left, &right, &points, &o);
        assert_eq!(m[0].distance, 0.0);
        assert!((f[0].x - 43.4).abs() < 1e-4 && (f[0].y - 38.0).abs() < 1e-4);
    }

    #[test]
    fn border_flat_and_cost_limit() {
        let left = plane(40, 40, 1.0, 0.0, (0.0, 0.0));
        // Near the border: the left patch leaves the image.
        let (m, f) = match_patches(&left, &left, &[kp(2.0, 20.0)], &options(Score::Zncc));
        assert!(m.is_empty() && f.is_empty());
        // Flat left patch: no correlation.
        let flat = Plane {
            width: 40,
            height: 40,
            data: vec![5.0; 1600],
        };
        let (m, _) = match_patches(&flat, &left, &[kp(20.0, 20.0)], &options(Score::Zncc));
        assert!(m.is_empty());
        // SSD on the flat image works, max_cost filters.
        let (m, _) = match_patches(&flat, &flat, &[kp(20.0, 20.0)], &options(Score::Ssd));
        assert_eq!(m.len(), 1);
        let right = plane(40, 40, 1.0, 50.0, (0.0, 0.0));
        let mut o = options(Score::Ssd);
        o.max_cost = Some(100.0);
        let (m, _) = match_patches(&left, &right, &[kp(20.0, 20.0)], &o);
        assert!(m.is_empty());
        // Empty keypoints and a 1×1 image.
        let tiny = Plane {
            width: 1,
            height: 1,
            data: vec![1.0],
        };
        let (m, _) = match_patches(&tiny, &tiny, &[kp(0.0, 0.0)], &options(Score::Ssd));
        assert!(m.is_empty());
        let mut o = options(Score::Ssd);
        o.half = 0;
        let (m, _) = match_patches(&tiny, &tiny, &[kp(0.0, 0.0)], &o);
        assert_eq!(m.len(), 1);
        assert!(match_patches(&left, &left, &[], &o).0.is_empty());
    }

    #[test]
    fn operator_checks() {
        assert!(
            PatchMatch::new(PatchParams {
                window_px: 4,
                ..PatchParams::default()
            })
            .is_err()
        );
        let op = PatchMatch::new(PatchParams::default()).unwrap();
        let specs = PatchMatch::inputs();
        let left = Image::from_u8(50, 50, Channels::Rgb, vec![7; 7500]).unwrap();
        let right = Image::from_f32(50, 50, Channels::Gray, vec![0.0; 2500]).unwrap();
        let values = vec![
            Some(Value::image(left.clone())),
            Some(Value::image(right)),
            Some(Value::Keypoints(vec![kp(25.0, 25.0)].into())),
        ];
        let ctx = RunContext {
            node: "p".into(),
            threads: 1,
            element: None,
        };
        let e = op.run(&ctx, &Inputs::new(&specs, &values)).err().unwrap();
        assert!(e.to_string().contains("sample type"), "{e}");
        let values = vec![
            Some(Value::image(left.clone())),
            Some(Value::image(left)),
            Some(Value::Keypoints(vec![kp(25.0, 25.0)].into())),
        ];
        // Flat images: no ZNCC match, but no error.
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        assert!(matches!(out.take("matches"), Some(Value::Matches(m)) if m.is_empty()));
    }
}
