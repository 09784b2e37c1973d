//! `match.brute_force`: exact two-nearest-neighbour descriptor matching with Lowe's ratio test,
//! cross-check, and optional spatial or epipolar restriction of the candidates.
//!
//! How it runs:
//! - Binary descriptors are packed into u64 words and the train set is laid out in tiles of
//!   [`TILE`] rows stored word-major (`tile[w][j]`), so the Hamming distances of one query to a
//!   whole tile are one vertical loop `dist[j] += popcount(q[w] ^ tile[w][j])` that compiles to
//!   SIMD popcounts. Distances are exact integers.
//! - Float descriptors use `‖q − t‖² = ‖q‖² + ‖t‖² − 2 q·t` with f32 dot products as a small
//!   matrix product, blocked over train rows for cache: with AVX2 and FMA, four queries × sixteen
//!   train rows at a time, the train rows packed in panels of eight so that each broadcast
//!   query element updates eight dot products in one fused multiply–add (`float_avx2`);
//!   otherwise four queries × two train rows in eight-lane accumulators. That value can be off
//!   by rounding (cancellation), so it
//!   only selects candidates: every train row whose approximate distance is within twice a
//!   proven rounding bound of the approximate second-nearest is re-measured with
//!   [`l2_squared_exact`], and the two nearest are picked from those exact values. The result
//!   is therefore exactly that of the naive search, ties included (lowest train index first).
//! - With a restriction (search window or epipolar band), each query's admissible train rows
//!   are listed first and measured exactly; no tiling is needed for the few candidates.
//! - Queries are processed in parallel in fixed chunks of [`QUERY_CHUNK`], each query's result
//!   depending only on its own data: results are identical for any thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Keypoint, Match, Matrix, Value};
use rayon::prelude::*;

use super::{
    DescriptorRows, Metric, Norm, Top2, descriptors, l2_squared_exact, optional_keypoints, prepare,
    ratio_accepts,
};

/// Queries per parallel task.
pub const QUERY_CHUNK: usize = 64;

/// Train rows per tile of the binary kernel.
pub const TILE: usize = 256;

/// Train rows per cache block of the float kernel.
const TRAIN_BLOCK: usize = 64;

/// Queries per float micro-kernel call.
const QR: usize = 4;

// The AVX2 kernel takes the same query groups, and train blocks that start on its panels.
#[cfg(target_arch = "x86_64")]
const _: () = assert!(
    QR == super::float_avx2::QUERIES && TRAIN_BLOCK.is_multiple_of(super::float_avx2::PANEL)
);

/// Beyond this magnitude the f32 norms could overflow: the float kernel measures every pair
/// exactly instead.
const LARGE_VALUE: f32 = 1e15;

params! {
    /// Parameters of `match.brute_force`.
    pub struct BruteForceParams {
        /// Lowe's ratio test: a match is kept if `d1 < ratio · d2` (nearest and second-nearest
        /// reported distances). 1 disables the test. Default 0.8.
        ratio: f64 = 0.8 => [above = 0.0, max = 1.0],
        /// Keep only mutual nearest neighbours (the query is also the train row's nearest
        /// query). Default false.
        cross_check: bool = false,
        /// Drop matches whose distance exceeds this (in the reported distance's unit: L2,
        /// squared L2 or bits). Default none.
        max_distance: Option<f64> = None => [min = 0.0],
        /// Distance: "auto" (L2 for float, Hamming for binary), "l2", "l2_squared" or
        /// "hamming". Default "auto".
        norm: Norm = Norm::Auto,
        /// Only train keypoints within this distance of the query keypoint's position are
        /// candidates, px; 0 turns the window off. Needs both keypoint inputs. Default 0.
        search_radius_px: f64 = 0.0 => [min = 0.0, unit = "px"],
        /// With the `fundamental` input: only train keypoints within this distance of the
        /// query's epipolar line are candidates, px. Default 2.
        epipolar_band_px: f64 = 2.0 => [min = 0.0, unit = "px"],
    }
}

/// Brute-force matcher (`match.brute_force`). See [`brute_force_match`].
#[derive(Debug, Clone, PartialEq)]
pub struct BruteForce {
    options: MatchOptions,
    norm: Norm,
    search_radius_px: f64,
    epipolar_band_px: f64,
}

/// What to keep of the nearest neighbours.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MatchOptions {
    /// Lowe's ratio (≥ 1 disables).
    pub ratio: f64,
    /// Mutual nearest neighbours only.
    pub cross_check: bool,
    /// Largest reported distance kept.
    pub max_distance: Option<f64>,
}

impl Default for MatchOptions {
    fn default() -> Self {
        MatchOptions {
            ratio: 0.8,
            cross_check: false,
            max_distance: None,
        }
    }
}

impl Op for BruteForce {
    type Params = BruteForceParams;
    const ID: &'static str = "match.brute_force";
    const SUMMARY: &'static str =
        "Exact nearest-neighbour descriptor matching with ratio test and cross-check.";
    const DOC: &'static str = r#"
Finds, for every query descriptor, the two nearest train descriptors by exhaustive search and
keeps the nearest if it passes Lowe's ratio test (`d1 < ratio · d2`, OpenCV's `knnMatch` with
k = 2 followed by the usual test; `ratio: 1` keeps every nearest neighbour), is within
`max_distance`, and with `cross_check` is also the train row's nearest query (mutual nearest
neighbours, OpenCV's `crossCheck`). Equal distances go to the lower index. A query with a
single candidate has no second neighbour and passes the ratio test.

Distances: float descriptors by L2 (reported as true, not squared, distance; `norm:
"l2_squared"` reports and tests squared distances), binary ones by Hamming bit count (`norm:
"l2"` reads binary rows as byte vectors, like OpenCV's NORM_L2 on CV_8U). Float distances are
computed exactly (f64 differences and sums in a fixed order); the fast f32 matrix-product form
‖q‖² + ‖t‖² − 2 q·t only preselects candidates within a proven rounding bound, so results
equal a naive search bit for bit. Hamming distances use SIMD popcounts over word-major tiles.

Restrictions (both need `query_keypoints` and `train_keypoints`, one per descriptor):
`search_radius_px > 0` admits train keypoints within that radius of the query's position (for
small motions); the `fundamental` input F (3×3, `x_trainᵀ F x_query = 0`) admits train
keypoints within `epipolar_band_px` of the query's epipolar line F·x (for calibrated stereo or
two-view geometry). The ratio test and cross-check then run among the admitted candidates.

Output: matches sorted by query index, `distance` as described. Empty descriptor sets give no
matches; descriptors of different kinds or widths are an error.

Reference: D. G. Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 2004
(ratio test); OpenCV `cv::BFMatcher` (`knnMatch`, `crossCheck`).

Example:
    "match": (op: "match.brute_force", inputs: { "query": "orb1.descriptors",
              "train": "orb2.descriptors" }, params: (ratio: 0.8)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "query",
                PortType::Descriptors,
                "Descriptors of the first view.",
            ),
            PortSpec::new(
                "train",
                PortType::Descriptors,
                "Descriptors of the second view, same kind and width.",
            ),
            PortSpec::new(
                "query_keypoints",
                PortType::Keypoints,
                "Keypoints of the query descriptors (for the restrictions).",
            )
            .optional(),
            PortSpec::new(
                "train_keypoints",
                PortType::Keypoints,
                "Keypoints of the train descriptors (for the restrictions).",
            )
            .optional(),
            PortSpec::new(
                "fundamental",
                PortType::Matrix,
                "Fundamental matrix F (3×3) with x_trainᵀ F x_query = 0: restricts candidates to \
                 the epipolar band.",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "matches",
            PortType::Matches,
            "Accepted matches, sorted by query index.",
        )]
    }

    fn new(params: BruteForceParams) -> Result<Self, String> {
        let BruteForceParams {
            ratio,
            cross_check,
            max_distance,
            norm,
            search_radius_px,
            epipolar_band_px,
        } = params;
        for (name, v) in [
            ("ratio", ratio),
            ("search_radius_px", search_radius_px),
            ("epipolar_band_px", epipolar_band_px),
            ("max_distance", max_distance.unwrap_or(0.0)),
        ] {
            if !v.is_finite() {
                return Err(format!("`{name}` must be finite, got {v}"));
            }
        }
        if !(ratio > 0.0 && ratio <= 1.0) {
            return Err(format!("`ratio` must be in (0, 1], got {ratio}"));
        }
        if search_radius_px < 0.0 || epipolar_band_px < 0.0 || max_distance.is_some_and(|d| d < 0.0)
        {
            return Err(
                "`search_radius_px`, `epipolar_band_px` and `max_distance` must be ≥ 0".into(),
            );
        }
        Ok(BruteForce {
            options: MatchOptions {
                ratio,
                cross_check,
                max_distance,
            },
            norm,
            search_radius_px,
            epipolar_band_px,
        })
    }
}

impl Operator for BruteForce {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let query = descriptors(inputs, "query")?;
        let train = descriptors(inputs, "train")?;
        let (metric, q, t) = prepare(query, train, self.norm)?;
        let fundamental = match inputs.get("fundamental") {
            None => None,
            Some(Value::Matrix(m)) => Some(fundamental_of(m)?),
            Some(other) => {
                return Err(OpError::input(
                    "fundamental",
                    format!("expected Matrix, got {}", other.port_type()),
                ));
            }
        };
        let restriction = if self.search_radius_px > 0.0 || fundamental.is_some() {
            let qk = optional_keypoints(inputs, "query_keypoints", q.len())?;
            let tk = optional_keypoints(inputs, "train_keypoints", t.len())?;
            let (Some(qk), Some(tk)) = (qk, tk) else {
                return Err(OpError::input(
                    "query_keypoints",
                    "search_radius_px > 0 or a fundamental matrix needs both query_keypoints \
                     and train_keypoints",
                ));
            };
            Some(Restriction::new(
                qk,
                tk,
                self.search_radius_px,
                fundamental.map(|f| (f, self.epipolar_band_px)),
            ))
        } else {
            None
        };
        let matches = brute_force_match(&q, &t, metric, &self.options, restriction.as_ref());
        Ok(Outputs::new().with("matches", Value::Matches(matches.into())))
    }
}

/// The 3×3 entries of a fundamental matrix input, row-major, checked finite.
fn fundamental_of(m: &Matrix) -> Result<[f64; 9], OpError> {
    if m.rows != 3 || m.cols != 3 || m.data.len() != 9 {
        return Err(OpError::input(
            "fundamental",
            format!("must be 3×3, got {}×{}", m.rows, m.cols),
        ));
    }
    if m.data.iter().any(|v| !v.is_finite()) {
        return Err(OpError::input("fundamental", "holds a non-finite entry"));
    }
    let mut f = [0.0; 9];
    f.copy_from_slice(&m.data);
    Ok(f)
}

/// Which (query, train) pairs may match: within a radius and / or an epipolar band.
#[derive(Debug, Clone)]
pub struct Restriction<'a> {
    query: &'a [Keypoint],
    train: &'a [Keypoint],
    radius_sq: Option<f64>,
    /// Per query: its epipolar line `(a, b, c)` scaled to unit normal (a² + b² = 1), or `None`
    /// where F·x vanishes (the query sits at the epipole: no constraint).
    lines: Option<(Vec<Option<[f64; 3]>>, f64)>,
}

impl<'a> Restriction<'a> {
    /// A restriction: `radius > 0` admits train keypoints with `‖t − q‖ ≤ radius`; `epipolar`
    /// `(F, band)` admits those with distance ≤ band to the line `F · (qx, qy, 1)`.
    pub fn new(
        query: &'a [Keypoint],
        train: &'a [Keypoint],
        radius: f64,
        epipolar: Option<([f64; 9], f64)>,
    ) -> Restriction<'a> {
        let lines = epipolar.map(|(f, band)| {
            let lines = query
                .iter()
                .map(|k| {
                    let (x, y) = (f64::from(k.x), f64::from(k.y));
                    let a = f[0] * x + f[1] * y + f[2];
                    let b = f[3] * x + f[4] * y + f[5];
                    let c = f[6] * x + f[7] * y + f[8];
                    let n = a.hypot(b);
                    (n > 0.0 && n.is_finite()).then(|| [a / n, b / n, c / n])
                })
                .collect();
            (lines, band)
        });
        Restriction {
            query,
            train,
            radius_sq: (radius > 0.0).then_some(radius * radius),
            lines,
        }
    }

    /// Whether query `q` may match train `t`.
    #[inline]
    pub fn allows(&self, q: usize, t: usize) -> bool {
        let (Some(a), Some(b)) = (self.query.get(q), self.train.get(t)) else {
            return false;
        };
        let (tx, ty) = (f64::from(b.x), f64::from(b.y));
        if let Some(r2) = self.radius_sq {
            let (dx, dy) = (tx - f64::from(a.x), ty - f64::from(a.y));
            if dx * dx + dy * dy > r2 {
                return false;
            }
        }
        if let Some((lines, band)) = &self.lines
            && let Some(Some([la, lb, lc])) = lines.get(q)
            && (la * tx + lb * ty + lc).abs() > *band
        {
            return false;
        }
        true
    }
}

/// Matches `query` against `train` (same kind and width, from [`prepare`]) under `metric`:
/// exact two nearest neighbours per query (restricted to the pairs `restriction` allows), then
/// the ratio test, `max_distance` and cross-check of `options`. Sorted by query index.
pub fn brute_force_match(
    query: &DescriptorRows<'_>,
    train: &DescriptorRows<'_>,
    metric: Metric,
    options: &MatchOptions,
    restriction: Option<&Restriction<'_>>,
) -> Vec<Match> {
    if query.is_empty() || train.is_empty() {
        return Vec::new();
    }
    let tops = match restriction {
        Some(r) => knn2_restricted(query, train, &|q, t| r.allows(q, t)),
        None => knn2(query, train),
    };
    let accepted: Vec<(usize, Top2)> = tops
        .into_iter()
        .enumerate()
        .filter(|(_, top)| {
            top.found()
                && ratio_accepts(top, metric, options.ratio)
                && options
                    .max_distance
                    .is_none_or(|m| f64::from(metric.report(top.d1)) <= m)
        })
        .collect();
    let keep: Vec<bool> = if options.cross_check {
        mutual(query, train, &accepted, restriction)
    } else {
        vec![true; accepted.len()]
    };
    accepted
        .iter()
        .zip(keep)
        .filter(|(_, k)| *k)
        .map(|(&(q, top), _)| Match {
            query: q as u32,
            train: top.i1,
            distance: metric.report(top.d1),
        })
        .collect()
}

/// For each accepted (query, nearest train): is the query also the train row's nearest query?
fn mutual(
    query: &DescriptorRows<'_>,
    train: &DescriptorRows<'_>,
    accepted: &[(usize, Top2)],
    restriction: Option<&Restriction<'_>>,
) -> Vec<bool> {
    let mut winners: Vec<usize> = accepted.iter().map(|(_, t)| t.i1 as usize).collect();
    winners.sort_unstable();
    winners.dedup();
    let sub = select_rows(train, &winners);
    let back = match restriction {
        Some(r) => knn2_restricted(&sub, query, &|s, q| r.allows(q, winners[s])),
        None => knn2(&sub, query),
    };
    accepted
        .iter()
        .map(|&(q, top)| {
            winners
                .binary_search(&(top.i1 as usize))
                .is_ok_and(|s| back[s].i1 as usize == q)
        })
        .collect()
}

/// The rows `indices` of `rows`, in that order.
pub fn select_rows(rows: &DescriptorRows<'_>, indices: &[usize]) -> DescriptorRows<'static> {
    match rows {
        DescriptorRows::Float { dim, data } => DescriptorRows::Float {
            dim: *dim,
            data: indices
                .iter()
                .flat_map(|&i| &data[i * dim..(i + 1) * dim])
                .copied()
                .collect::<Vec<f32>>()
                .into(),
        },
        DescriptorRows::Binary { words, data } => DescriptorRows::Binary {
            words: *words,
            data: indices
                .iter()
                .flat_map(|&i| &data[i * words..(i + 1) * words])
                .copied()
                .collect(),
        },
    }
}

/// Exact two nearest train rows of every query (squared L2 or Hamming; ties to the lower
/// index). Rows must be of the same kind and width.
pub fn knn2(query: &DescriptorRows<'_>, train: &DescriptorRows<'_>) -> Vec<Top2> {
    match (query, train) {
        (DescriptorRows::Binary { words, data: q }, DescriptorRows::Binary { data: t, .. }) => {
            knn2_binary(q, t, *words)
        }
        (DescriptorRows::Float { dim, data: q }, DescriptorRows::Float { data: t, .. }) => {
            knn2_float(q, t, *dim)
        }
        _ => vec![Top2::default(); query.len()],
    }
}

/// Two nearest neighbours among the pairs `allowed(query, train)` admits, measured exactly.
pub fn knn2_restricted(
    query: &DescriptorRows<'_>,
    train: &DescriptorRows<'_>,
    allowed: &(dyn Fn(usize, usize) -> bool + Sync),
) -> Vec<Top2> {
    let mut out = vec![Top2::default(); query.len()];
    let nt = train.len();
    out.par_chunks_mut(QUERY_CHUNK)
        .enumerate()
        .for_each(|(c, tops)| {
            for (i, top) in tops.iter_mut().enumerate() {
                let q = c * QUERY_CHUNK + i;
                for t in 0..nt {
                    if allowed(q, t) {
                        top.offer(query.distance(q, train, t), t as u32);
                    }
                }
            }
        });
    out
}

/// Binary kernel: word-major tiles of the train set, SIMD popcounts.
fn knn2_binary(q: &[u64], t: &[u64], words: usize) -> Vec<Top2> {
    let nq = q.len() / words;
    let nt = t.len() / words;
    let tiles = nt.div_ceil(TILE);
    let mut tiled = vec![0u64; tiles * words * TILE];
    for j in 0..nt {
        let (tile, lane) = (j / TILE, j % TILE);
        for w in 0..words {
            tiled[(tile * words + w) * TILE + lane] = t[j * words + w];
        }
    }
    let mut out = vec![Top2::default(); nq];
    out.par_chunks_mut(QUERY_CHUNK)
        .enumerate()
        .for_each(|(c, tops)| {
            let q0 = c * QUERY_CHUNK;
            let mut best = vec![[u32::MAX, u32::MAX, u32::MAX, u32::MAX]; tops.len()];
            let mut dist = [0u32; TILE];
            for tile in 0..tiles {
                let block = &tiled[tile * words * TILE..(tile + 1) * words * TILE];
                let base = tile * TILE;
                let valid = (nt - base).min(TILE);
                for (i, b) in best.iter_mut().enumerate() {
                    let qrow = &q[(q0 + i) * words..(q0 + i + 1) * words];
                    hamming_tile(qrow, block, &mut dist);
                    // [d1, i1, d2, i2]; indices rise, so strict `<` keeps the lowest on ties.
                    for (j, &d) in dist[..valid].iter().enumerate() {
                        if d < b[2] {
                            let idx = (base + j) as u32;
                            if d < b[0] {
                                *b = [d, idx, b[0], b[1]];
                            } else {
                                b[2] = d;
                                b[3] = idx;
                            }
                        }
                    }
                }
            }
            for (top, b) in tops.iter_mut().zip(best) {
                if b[1] != u32::MAX {
                    top.d1 = f64::from(b[0]);
                    top.i1 = b[1];
                }
                if b[3] != u32::MAX {
                    top.d2 = f64::from(b[2]);
                    top.i2 = b[3];
                }
            }
        });
    out
}

/// Hamming distances of one query row to the [`TILE`] rows of a word-major tile.
#[multiversion::multiversion(targets("x86_64+avx2+popcnt", "x86_64+sse4.2+popcnt"))]
fn hamming_tile(q: &[u64], tile: &[u64], dist: &mut [u32; TILE]) {
    dist.fill(0);
    for (&qw, column) in q.iter().zip(tile.chunks_exact(TILE)) {
        for (d, &tw) in dist.iter_mut().zip(column) {
            *d += (qw ^ tw).count_ones();
        }
    }
}

/// Float kernel: f32 matrix-product preselection, exact re-measurement of the candidates.
fn knn2_float(q: &[f32], t: &[f32], dim: usize) -> Vec<Top2> {
    let nq = q.len() / dim;
    let nt = t.len() / dim;
    let max_abs = q.iter().chain(t).fold(0.0f32, |m, v| m.max(v.abs()));
    if max_abs > LARGE_VALUE {
        let (qr, tr) = (
            DescriptorRows::Float {
                dim,
                data: q.into(),
            },
            DescriptorRows::Float {
                dim,
                data: t.into(),
            },
        );
        return knn2_restricted(&qr, &tr, &|_, _| true);
    }
    let dp = dim.next_multiple_of(8);
    // Train rows padded to `dp` floats, row count padded to even (zero rows never reported).
    let nt_pad = nt.next_multiple_of(2);
    let mut tpad = vec![0.0f32; nt_pad * dp];
    for (dst, src) in tpad.chunks_exact_mut(dp).zip(t.chunks_exact(dim)) {
        dst[..dim].copy_from_slice(src);
    }
    let tnorm: Vec<f32> = tpad.chunks_exact(dp).map(|r| dot(r, r)).collect();
    let tmax = tnorm.iter().fold(0.0f64, |m, &v| m.max(f64::from(v)));
    // Rounding bound of the f32 form against the exact value (see the module doc): products
    // and sums of `dim / 8` terms per lane, an 8-lane reduction and the two final additions,
    // each contributing at most one unit roundoff of `‖q‖² + ‖t‖²`; doubled for safety, plus
    // an absolute term for underflow.
    let unit = (dim as f64 + 16.0) * f64::powi(2.0, -23);
    #[cfg(target_arch = "x86_64")]
    let panels =
        super::float_avx2::available().then(|| super::float_avx2::Panels::new(t, dim, &tnorm));
    let mut out = vec![Top2::default(); nq];
    out.par_chunks_mut(QUERY_CHUNK)
        .enumerate()
        .for_each(|(c, tops)| {
            let q0 = c * QUERY_CHUNK;
            let n = tops.len();
            let n_pad = n.next_multiple_of(QR);
            let mut qpad = vec![0.0f32; n_pad * dp];
            for (i, dst) in qpad.chunks_exact_mut(dp).take(n).enumerate() {
                dst[..dim].copy_from_slice(&q[(q0 + i) * dim..(q0 + i + 1) * dim]);
            }
            let qnorm: Vec<f32> = qpad.chunks_exact(dp).map(|r| dot(r, r)).collect();
            let mut approx = vec![0.0f32; n_pad * nt];
            for t0 in (0..nt).step_by(TRAIN_BLOCK) {
                let t1 = (t0 + TRAIN_BLOCK).min(nt);
                let t1_pad = t1.next_multiple_of(2);
                for g in (0..n_pad).step_by(QR) {
                    #[cfg(target_arch = "x86_64")]
                    if let Some(panels) = &panels
                        && super::float_avx2::approx_block(
                            &qpad[g * dp..(g + QR) * dp],
                            dp,
                            &qnorm[g..g + QR],
                            panels,
                            &mut approx[g * nt..(g + QR) * nt],
                            nt,
                            t0,
                            t1,
                        )
                    {
                        continue;
                    }
                    approx_block(
                        &qpad[g * dp..(g + QR) * dp],
                        &qnorm[g..g + QR],
                        &tpad[t0 * dp..t1_pad * dp],
                        &tnorm[t0..t1_pad],
                        dp,
                        &mut approx[g * nt..(g + QR) * nt],
                        nt,
                        t0,
                        t1,
                    );
                }
            }
            for (i, top) in tops.iter_mut().enumerate() {
                let row = &approx[i * nt..(i + 1) * nt];
                let (mut a1, mut a2) = (f32::INFINITY, f32::INFINITY);
                for &a in row {
                    if a < a2 {
                        if a < a1 {
                            a2 = a1;
                            a1 = a;
                        } else {
                            a2 = a;
                        }
                    }
                }
                let delta = unit * (f64::from(qnorm[i]) + tmax) + 1e-30;
                let limit = f64::from(a2) + 2.0 * delta;
                let qrow = &q[(q0 + i) * dim..(q0 + i + 1) * dim];
                for (j, &a) in row.iter().enumerate() {
                    if f64::from(a) <= limit {
                        let d = l2_squared_exact(qrow, &t[j * dim..(j + 1) * dim]);
                        top.offer(d, j as u32);
                    }
                }
            }
        });
    out
}

/// Dot product in eight lanes, reduced pairwise: `((l0+l4)+(l2+l6)) + ((l1+l5)+(l3+l7))`.
#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    for (x, y) in a.chunks_exact(8).zip(b.chunks_exact(8)) {
        for l in 0..8 {
            acc[l] += x[l] * y[l];
        }
    }
    reduce8(&acc)
}

#[inline(always)]
fn reduce8(a: &[f32; 8]) -> f32 {
    ((a[0] + a[4]) + (a[2] + a[6])) + ((a[1] + a[5]) + (a[3] + a[7]))
}

/// Approximate squared distances `‖q‖² + ‖t‖² − 2 q·t` of [`QR`] padded query rows against
/// train rows `t0..t1` (given from `t0`, padded to an even count), into `out[i * stride + j]`.
#[allow(clippy::too_many_arguments)]
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+sse4.1"))]
fn approx_block(
    q: &[f32],
    qnorm: &[f32],
    t: &[f32],
    tnorm: &[f32],
    dp: usize,
    out: &mut [f32],
    stride: usize,
    t0: usize,
    t1: usize,
) {
    let (q0, rest) = q.split_at(dp);
    let (q1, rest) = rest.split_at(dp);
    let (q2, q3) = rest.split_at(dp);
    for (p, pair) in t.chunks_exact(2 * dp).enumerate() {
        let (r0, r1) = pair.split_at(dp);
        let mut acc = [[0.0f32; 8]; 8];
        for ((((a0, a1), a2), a3), (b0, b1)) in q0
            .chunks_exact(8)
            .zip(q1.chunks_exact(8))
            .zip(q2.chunks_exact(8))
            .zip(q3.chunks_exact(8))
            .zip(r0.chunks_exact(8).zip(r1.chunks_exact(8)))
        {
            for l in 0..8 {
                acc[0][l] += a0[l] * b0[l];
                acc[1][l] += a0[l] * b1[l];
                acc[2][l] += a1[l] * b0[l];
                acc[3][l] += a1[l] * b1[l];
                acc[4][l] += a2[l] * b0[l];
                acc[5][l] += a2[l] * b1[l];
                acc[6][l] += a3[l] * b0[l];
                acc[7][l] += a3[l] * b1[l];
            }
        }
        for (s, a) in acc.iter().enumerate() {
            let (i, jj) = (s / 2, s % 2);
            let j = t0 + 2 * p + jj;
            if j < t1 {
                out[i * stride + j] = qnorm[i] + tnorm[2 * p + jj] - 2.0 * reduce8(a);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_support::{random_binary, random_float, stream};
    use super::super::{Norm, prepare};
    use super::*;
    use ocellus_engine::value::Descriptors;
    use proptest::prelude::*;

    /// Naive reference: every pair measured exactly, strict `<` in index order.
    fn naive(
        q: &DescriptorRows<'_>,
        t: &DescriptorRows<'_>,
        metric: Metric,
        options: &MatchOptions,
        allowed: &dyn Fn(usize, usize) -> bool,
    ) -> Vec<Match> {
        let nn = |a: &DescriptorRows<'_>, b: &DescriptorRows<'_>, i: usize, flip: bool| {
            let (mut d1, mut i1, mut d2, mut i2) = (f64::INFINITY, None, f64::INFINITY, None);
            for j in 0..b.len() {
                let ok = if flip { allowed(j, i) } else { allowed(i, j) };
                if !ok {
                    continue;
                }
                let d = a.distance(i, b, j);
                if d < d1 {
                    (d2, i2, d1, i1) = (d1, i1, d, Some(j));
                } else if d < d2 {
                    (d2, i2) = (d, Some(j));
                }
            }
            (d1, i1, d2, i2)
        };
        let mut out = Vec::new();
        for i in 0..q.len() {
            let (d1, i1, d2, i2) = nn(q, t, i, false);
            let Some(j) = i1 else { continue };
            let r1 = metric.report(d1);
            if i2.is_some()
                && options.ratio < 1.0
                && (f64::from(r1) >= options.ratio * f64::from(metric.report(d2)))
            {
                continue;
            }
            if options.max_distance.is_some_and(|m| f64::from(r1) > m) {
                continue;
            }
            if options.cross_check && nn(t, q, j, true).1 != Some(i) {
                continue;
            }
            out.push(Match {
                query: i as u32,
                train: j as u32,
                distance: r1,
            });
        }
        out
    }

    fn run(q: &Descriptors, t: &Descriptors, norm: Norm, options: &MatchOptions) -> Vec<Match> {
        let (metric, qr, tr) = prepare(q, t, norm).unwrap();
        let ours = brute_force_match(&qr, &tr, metric, options, None);
        let reference = naive(&qr, &tr, metric, options, &|_, _| true);
        assert_eq!(ours, reference);
        ours
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]

        #[test]
        fn binary_equals_naive(
            nq in 0usize..150, nt in 0usize..600, bytes in 1usize..40, seed in 0u64..1000,
            ratio in prop::sample::select(vec![0.6, 0.8, 1.0]), cross in any::<bool>(),
        ) {
            let q = random_binary(nq, bytes, seed);
            // Few distinct rows make ties likely.
            let t = random_binary(nt, bytes, seed + 1);
            let options = MatchOptions { ratio, cross_check: cross, max_distance: None };
            run(&q, &t, Norm::Auto, &options);
        }

        #[test]
        fn float_equals_naive(
            nq in 0usize..150, nt in 0usize..300, dim in 1usize..70, levels in 2u64..6,
            seed in 0u64..1000, ratio in prop::sample::select(vec![0.7, 0.9, 1.0]),
            cross in any::<bool>(), max in prop::option::of(0.5f64..3.0),
        ) {
            let q = random_float(nq, dim, levels, seed);
            let t = random_float(nt, dim, levels, seed + 7);
            let options = MatchOptions { ratio, cross_check: cross, max_distance: max };
            run(&q, &t, Norm::Auto, &options);
            run(&q, &t, Norm::L2Squared, &options);
        }
    }

    /// The AVX2 kernel's approximate distances and the portable kernel's both lie within the
    /// matcher's rounding bound of the exact value, for any dimension, block and tail.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_kernel_stays_within_the_rounding_bound() {
        use crate::matching::float_avx2;
        if !float_avx2::available() {
            return;
        }
        let mut next = stream(11);
        for (dim, nt) in [
            (128usize, 77usize),
            (1, 9),
            (7, 8),
            (8, 17),
            (70, 64),
            (33, 130),
            (128, 3),
        ] {
            let dp = dim.next_multiple_of(8);
            let mut value = || (next() % 1000) as f32 * 0.37 - 50.0;
            let q: Vec<f32> = (0..QR * dim).map(|_| value()).collect();
            let t: Vec<f32> = (0..nt * dim).map(|_| value()).collect();
            let mut qpad = vec![0.0f32; QR * dp];
            for (dst, src) in qpad.chunks_exact_mut(dp).zip(q.chunks_exact(dim)) {
                dst[..dim].copy_from_slice(src);
            }
            let nt_pad = nt.next_multiple_of(2);
            let mut tpad = vec![0.0f32; nt_pad * dp];
            for (dst, src) in tpad.chunks_exact_mut(dp).zip(t.chunks_exact(dim)) {
                dst[..dim].copy_from_slice(src);
            }
            let qnorm: Vec<f32> = qpad.chunks_exact(dp).map(|r| dot(r, r)).collect();
            let tnorm: Vec<f32> = tpad.chunks_exact(dp).map(|r| dot(r, r)).collect();
            let panels = float_avx2::Panels::new(&t, dim, &tnorm);
            let (mut fast, mut portable) = (vec![f32::NAN; QR * nt], vec![f32::NAN; QR * nt]);
            // Blocks of 40 rows: two panel pairs and a single panel, then shorter tails.
            for t0 in (0..nt).step_by(40) {
                let t1 = (t0 + 40).min(nt);
                assert!(float_avx2::approx_block(
                    &qpad, dp, &qnorm, &panels, &mut fast, nt, t0, t1
                ));
                approx_block(
                    &qpad,
                    &qnorm,
                    &tpad[t0 * dp..t1.next_multiple_of(2) * dp],
                    &tnorm[t0..t1.next_multiple_of(2)],
                    dp,
                    &mut portable,
                    nt,
                    t0,
                    t1,
                );
            }
            let tmax = tnorm.iter().fold(0.0f64, |m, &v| m.max(f64::from(v)));
            let unit = (dim as f64 + 16.0) * f64::powi(2.0, -23);
            for i in 0..QR {
                let bound = unit * (f64::from(qnorm[i]) + tmax) + 1e-30;
                for j in 0..nt {
                    let exact =
                        l2_squared_exact(&q[i * dim..(i + 1) * dim], &t[j * dim..(j + 1) * dim]);
                    for (kernel, v) in [
                        ("avx2", fast[i * nt + j]),
                        ("portable", portable[i * nt + j]),
                    ] {
                        let err = (f64::from(v) - exact).abs();
                        assert!(
                            err <= bound,
                            "{kernel} dim {dim} ({i}, {j}): {v} vs {exact}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn sift_like_equals_naive() {
        // Non-negative, large-norm data like SIFT (cancellation in ‖q‖²+‖t‖²−2q·t).
        let mut next = stream(5);
        let mut rows = |n: usize| Descriptors::Float {
            dim: 128,
            data: (0..n * 128).map(|_| (next() % 200) as f32 + 0.5).collect(),
        };
        let (q, t) = (rows(300), rows(700));
        let m = run(&q, &t, Norm::L2, &MatchOptions::default());
        let all = run(
            &q,
            &t,
            Norm::L2,
            &MatchOptions {
                ratio: 1.0,
                ..MatchOptions::default()
            },
        );
        assert_eq!(all.len(), 300);
        assert!(m.len() <= all.len());
        // Near-duplicates: t = q + tiny noise, found exactly.
        let Descriptors::Float { data: qd, .. } = &q else {
            unreachable!()
        };
        let t2 = Descriptors::Float {
            dim: 128,
            data: qd.iter().map(|v| v + 0.001).collect(),
        };
        let m = run(&q, &t2, Norm::L2, &MatchOptions::default());
        assert_eq!(m.len(), 300);
        assert!(m.iter().all(|m| m.query == m.train));
    }

    #[test]
    fn binary_as_l2_and_large_floats() {
        let q = random_binary(40, 8, 3);
        let t = random_binary(90, 8, 4);
        run(&q, &t, Norm::L2, &MatchOptions::default());
        let big = |s: u64| {
            let mut next = stream(s);
            Descriptors::Float {
                dim: 3,
                data: (0..60).map(|_| (next() % 7) as f32 * 1e30).collect(),
            }
        };
        run(&big(1), &big(2), Norm::L2, &MatchOptions::default());
    }

    #[test]
    fn hamming_hand_case_and_ties() {
        let q = Descriptors::Binary {
            bytes: 1,
            data: vec![0b0000_0000, 0b1111_1111],
        };
        let t = Descriptors::Binary {
            bytes: 1,
            data: vec![0b0000_0111, 0b0000_0001, 0b1000_0000, 0b1111_1110],
        };
        let m = run(
            &q,
            &t,
            Norm::Auto,
            &MatchOptions {
                ratio: 1.0,
                ..MatchOptions::default()
            },
        );
        // Query 0: train 1 and 2 both at 1 bit: the lower index wins.
        assert_eq!(
            m[0],
            Match {
                query: 0,
                train: 1,
                distance: 1.0
            }
        );
        assert_eq!(
            m[1],
            Match {
                query: 1,
                train: 3,
                distance: 1.0
            }
        );
        // Ratio 0.8: query 0 has d1 = d2 = 1 and fails; query 1 has d1 = 1, d2 = 5 (train 0).
        let m = run(&q, &t, Norm::Auto, &MatchOptions::default());
        assert_eq!(m.len(), 1);
        assert_eq!(m[0].query, 1);
    }

    #[test]
    fn cross_check_is_symmetric() {
        let a = random_binary(200, 32, 11);
        let b = random_binary(230, 32, 12);
        let options = MatchOptions {
            ratio: 1.0,
            cross_check: true,
            max_distance: None,
        };
        let ab = run(&a, &b, Norm::Auto, &options);
        let ba = run(&b, &a, Norm::Auto, &options);
        let mut flipped: Vec<(u32, u32)> = ba.iter().map(|m| (m.train, m.query)).collect();
        flipped.sort_unstable();
        let pairs: Vec<(u32, u32)> = ab.iter().map(|m| (m.query, m.train)).collect();
        assert_eq!(pairs, flipped);
        assert!(!pairs.is_empty());
    }

    fn kp(x: f32, y: f32) -> Keypoint {
        Keypoint {
            x,
            y,
            size: 1.0,
            angle: -1.0,
            response: 0.0,
            octave: 0,
        }
    }

    #[test]
    fn window_restriction() {
        // All train descriptors equal to the query except train 0 (closest by descriptor) far
        // away: the window picks the near keypoint.
        let q = Descriptors::Float {
            dim: 2,
            data: vec![0.0, 0.0],
        };
        let t = Descriptors::Float {
            dim: 2,
            data: vec![0.0, 0.0, 1.0, 0.0, 2.0, 0.0],
        };
        let qk = [kp(10.0, 10.0)];
        let tk = [kp(100.0, 100.0), kp(13.0, 14.0), kp(11.0, 10.0)];
        let (metric, qr, tr) = prepare(&q, &t, Norm::Auto).unwrap();
        let options = MatchOptions {
            ratio: 1.0,
            ..MatchOptions::default()
        };
        let r = Restriction::new(&qk, &tk, 5.0, None);
        let m = brute_force_match(&qr, &tr, metric, &options, Some(&r));
        assert_eq!(m[0].train, 1);
        // Radius 4.9 excludes train 1 (distance 5).
        let r = Restriction::new(&qk, &tk, 4.9, None);
        let m = brute_force_match(&qr, &tr, metric, &options, Some(&r));
        assert_eq!(m[0].train, 2);
        let m = naive(&qr, &tr, metric, &options, &|a, b| r.allows(a, b));
        assert_eq!(m[0].train, 2);
        let r = Restriction::new(&qk, &tk, 0.5, None);
        assert!(brute_force_match(&qr, &tr, metric, &options, Some(&r)).is_empty());
    }

    #[test]
    fn epipolar_restriction() {
        // Rectified stereo: F = [[0,0,0],[0,0,-1],[0,1,0]] gives the line y' = y.
        let f = [0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0];
        let qk = [kp(50.0, 20.0), kp(10.0, 40.0)];
        let tk = [kp(45.0, 30.0), kp(40.0, 21.5), kp(5.0, 40.2), kp(0.0, 20.0)];
        let q = random_float(2, 16, 5, 1);
        let t = random_float(4, 16, 5, 2);
        let (metric, qr, tr) = prepare(&q, &t, Norm::Auto).unwrap();
        let r = Restriction::new(&qk, &tk, 0.0, Some((f, 2.0)));
        let admitted: Vec<(usize, usize)> = (0..2)
            .flat_map(|a| (0..4).map(move |b| (a, b)))
            .filter(|&(a, b)| r.allows(a, b))
            .collect();
        assert_eq!(admitted, vec![(0, 1), (0, 3), (1, 2)]);
        for cross in [false, true] {
            let options = MatchOptions {
                ratio: 1.0,
                cross_check: cross,
                max_distance: None,
            };
            let ours = brute_force_match(&qr, &tr, metric, &options, Some(&r));
            let reference = naive(&qr, &tr, metric, &options, &|a, b| r.allows(a, b));
            assert_eq!(ours, reference);
        }
        let options = MatchOptions {
            ratio: 1.0,
            ..MatchOptions::default()
        };
        let m = brute_force_match(&qr, &tr, metric, &options, Some(&r));
        assert_eq!(m[1].train, 2);
        // Band 0.1 drops (0, 1) (1.5 px off the line) and (1, 2).
        let r = Restriction::new(&qk, &tk, 0.0, Some((f, 0.1)));
        let m = brute_force_match(&qr, &tr, metric, &options, Some(&r));
        assert_eq!(m.len(), 1);
        assert_eq!((m[0].query, m[0].train), (0, 3));
    }

    fn run_op(params: BruteForceParams, inputs: Vec<(&str, Value)>) -> Result<Vec<Match>, OpError> {
        let op = BruteForce::new(params).map_err(OpError::failed)?;
        let specs = BruteForce::inputs();
        let values: Vec<Option<Value>> = specs
            .iter()
            .map(|s| {
                inputs
                    .iter()
                    .find(|(n, _)| *n == s.name)
                    .map(|(_, v)| v.clone())
            })
            .collect();
        let ctx = RunContext {
            node: "m".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values))?;
        match out.take("matches") {
            Some(Value::Matches(m)) => Ok(m.to_vec()),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn operator_empty_mismatch_and_params() {
        let d = |x: Descriptors| Value::Descriptors(x.into());
        let empty = Descriptors::Float {
            dim: 128,
            data: vec![],
        };
        let some = random_float(5, 128, 4, 1);
        let m = run_op(
            BruteForceParams::default(),
            vec![("query", d(empty.clone())), ("train", d(some.clone()))],
        )
        .unwrap();
        assert!(m.is_empty());
        let m = run_op(
            BruteForceParams::default(),
            vec![("query", d(some.clone())), ("train", d(empty))],
        )
        .unwrap();
        assert!(m.is_empty());
        let e = run_op(
            BruteForceParams::default(),
            vec![
                ("query", d(some.clone())),
                ("train", d(random_float(5, 64, 4, 1))),
            ],
        )
        .unwrap_err();
        assert!(e.to_string().contains("same kind and width"), "{e}");
        // Restriction without keypoints is an error.
        let params = BruteForceParams {
            search_radius_px: 5.0,
            ..BruteForceParams::default()
        };
        let e = run_op(
            params,
            vec![("query", d(some.clone())), ("train", d(some.clone()))],
        )
        .unwrap_err();
        assert!(e.to_string().contains("keypoints"), "{e}");
        // Identical sets with ratio 1 match each row to itself.
        let params = BruteForceParams {
            ratio: 1.0,
            cross_check: true,
            ..BruteForceParams::default()
        };
        let m = run_op(params, vec![("query", d(some.clone())), ("train", d(some))]).unwrap();
        assert_eq!(m.len(), 5);
        assert!(m.iter().all(|m| m.query == m.train && m.distance == 0.0));
        for bad in [0.0, 1.5, f64::NAN] {
            assert!(
                BruteForce::new(BruteForceParams {
                    ratio: bad,
                    ..BruteForceParams::default()
                })
                .is_err()
            );
        }
        assert!(
            BruteForce::new(BruteForceParams {
                max_distance: Some(f64::INFINITY),
                ..BruteForceParams::default()
            })
            .is_err()
        );
    }

    #[test]
    fn thread_count_does_not_matter() {
        let q = random_float(300, 32, 4, 9);
        let t = random_float(500, 32, 4, 10);
        let (metric, qr, tr) = prepare(&q, &t, Norm::Auto).unwrap();
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| brute_force_match(&qr, &tr, metric, &MatchOptions::default(), None));
        let many = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap()
            .install(|| brute_force_match(&qr, &tr, metric, &MatchOptions::default(), None));
        assert_eq!(one, many);
    }
}
