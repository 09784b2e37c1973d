//! 2-D Delaunay triangulation: `mesh.delaunay_2d`, by the `spade` crate (exact orientation and
//! in-circle predicates after Shewchuk, "Adaptive precision floating-point arithmetic and fast
//! robust geometric predicates", DCG 1997; bulk loading by a sweep-hull construction followed
//! by Lawson flips).
//!
//! [`delaunay_2d`] merges duplicate points (the first occurrence is kept; `-0.0` and `0.0` are
//! the same), triangulates the distinct points and returns the triangles counter-clockwise
//! (positive signed area), each rotated to start at its smallest index and sorted, so the
//! output does not depend on spade's internal order. Spade is single-threaded: the result is the
//! same for any thread count. For cocircular points (a square grid) the Delaunay triangulation
//! is not unique; spade's deterministic choice is returned.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Mesh, Metrics, Value};
use spade::{DelaunayTriangulation, HasPosition, Point2, Triangulation};

/// Why no triangulation could be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DelaunayError {
    /// Fewer than 3 distinct points.
    #[error("a triangulation needs at least 3 distinct points, got {distinct} ({points} given)")]
    TooFewPoints {
        /// Points given.
        points: usize,
        /// Distinct points among them.
        distinct: usize,
    },
    /// A coordinate is NaN or infinite.
    #[error("point {index} is not finite")]
    NonFinite {
        /// Index of the first bad point.
        index: usize,
    },
    /// A coordinate is beyond what the exact predicates support.
    #[error(
        "point {index} has a coordinate beyond ±2^201, which the exact predicates cannot handle"
    )]
    TooLarge {
        /// Index of the first bad point.
        index: usize,
    },
    /// All points lie on one line.
    #[error("all {0} distinct points are collinear: there is no triangle")]
    Collinear(usize),
    /// Too many points for 32-bit indices.
    #[error("{0} points do not fit 32-bit indices")]
    TooMany(usize),
    /// Spade refused the input.
    #[error("triangulation failed: {0}")]
    Spade(String),
}

/// A Delaunay triangulation of distinct points.
#[derive(Debug, Clone, PartialEq)]
pub struct Triangulation2d {
    /// Input index of each vertex (first occurrences of distinct points, ascending).
    pub vertices: Vec<u32>,
    /// Triangles over `vertices` (indices into it), counter-clockwise, sorted.
    pub triangles: Vec<[u32; 3]>,
    /// Vertices on the convex hull boundary (including points in the middle of hull edges).
    pub hull_vertices: usize,
    /// Input points merged into an earlier identical point.
    pub duplicates: usize,
    /// Total area (that of the convex hull).
    pub area: f64,
}

/// A spade vertex remembering its index in `vertices`.
#[derive(Debug, Clone, Copy)]
struct Vertex {
    p: Point2<f64>,
    i: u32,
}

impl HasPosition for Vertex {
    type Scalar = f64;
    fn position(&self) -> Point2<f64> {
        self.p
    }
}

/// The Delaunay triangulation of `points` (see the module documentation).
pub fn delaunay_2d(points: &[[f64; 2]]) -> Result<Triangulation2d, DelaunayError> {
    let n = points.len();
    if u32::try_from(n).is_err() {
        return Err(DelaunayError::TooMany(n));
    }
    for (index, p) in points.iter().enumerate() {
        if !p.iter().all(|c| c.is_finite()) {
            return Err(DelaunayError::NonFinite { index });
        }
        if p.iter().any(|c| c.abs() > spade::MAX_ALLOWED_VALUE) {
            return Err(DelaunayError::TooLarge { index });
        }
    }
    // Distinct points, first occurrence kept (`+ 0.0` turns −0 into +0).
    let key = |i: usize| points[i].map(|c| (c + 0.0).to_bits());
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_unstable_by_key(|&i| (key(i), i));
    let mut keep = vec![false; n];
    for (k, &i) in order.iter().enumerate() {
        keep[i] = k == 0 || key(order[k - 1]) != key(i);
    }
    let vertices: Vec<u32> = (0..n as u32).filter(|&i| keep[i as usize]).collect();
    let distinct = vertices.len();
    if distinct < 3 {
        return Err(DelaunayError::TooFewPoints {
            points: n,
            distinct,
        });
    }
    let input: Vec<Vertex> = vertices
        .iter()
        .enumerate()
        .map(|(k, &i)| {
            let [x, y] = points[i as usize];
            Vertex {
                // Coordinates below 2^-142 would underflow the predicates: they become 0.
                p: spade::mitigate_underflow(Point2::new(x, y)),
                i: k as u32,
            }
        })
        .collect();
    let dt: DelaunayTriangulation<Vertex> = DelaunayTriangulation::bulk_load_stable(input)
        .map_err(|e| DelaunayError::Spade(format!("{e:?}")))?;
    if dt.num_vertices() != distinct {
        // Only flushed sub-2^-142 coordinates can collide here.
        return Err(DelaunayError::Spade(format!(
            "{} of {distinct} distinct points coincide after flushing coordinates below 2^-142",
            distinct - dt.num_vertices()
        )));
    }
    if dt.all_vertices_on_line() || dt.num_inner_faces() == 0 {
        return Err(DelaunayError::Collinear(distinct));
    }
    let mut triangles: Vec<[u32; 3]> = dt
        .inner_faces()
        .map(|f| {
            let t = f.vertices().map(|v| v.data().i);
            let r = (0..3).min_by_key(|&k| t[k]).unwrap_or(0);
            [t[r], t[(r + 1) % 3], t[(r + 2) % 3]]
        })
        .collect();
    triangles.sort_unstable();
    let area = triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|k| points[vertices[k as usize] as usize]);
            0.5 * ((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))
        })
        .sum();
    Ok(Triangulation2d {
        hull_vertices: dt.convex_hull_size(),
        duplicates: n - distinct,
        vertices,
        triangles,
        area,
    })
}

params! {
    /// Parameters of `mesh.delaunay_2d` (none).
    pub struct Delaunay2dParams {}
}

/// `mesh.delaunay_2d`. See [`delaunay_2d`].
#[derive(Debug, Clone, PartialEq)]
pub struct Delaunay2d;

impl Op for Delaunay2d {
    type Params = Delaunay2dParams;
    const ID: &'static str = "mesh.delaunay_2d";
    const SUMMARY: &'static str = "The Delaunay triangulation of 2-D points, as a flat mesh (z = 0) of counter-clockwise triangles.";
    const DOC: &'static str = r#"
Triangulates 2-D points so that no point lies inside the circumcircle of any triangle (Delaunay;
the triangulation maximizing the smallest angle), with the `spade` crate's exact predicates
(Shewchuk, DCG 1997), so nearly collinear or cocircular points and coordinates far from the
origin are handled exactly. Duplicate points are merged (the first occurrence is kept; metric
`duplicates_merged`). A triangulation of n distinct points with h on the hull boundary has
2n − 2 − h triangles covering the convex hull.

Output: `mesh`, the distinct points (in input order, z = 0, as f32) and triangles
counter-clockwise seen from +z (normals +z), sorted; `metrics`. Fewer than 3 distinct points,
all points on one line, and non-finite coordinates are errors. For cocircular points (a grid)
the triangulation is not unique; the result is deterministic.

Metrics: `points`, `vertices` (distinct points), `duplicates_merged`, `triangles`,
`hull_vertices`, `area`.

Example:
    "tri": (op: "mesh.delaunay_2d", inputs: { "points": "corners.corners" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "points",
            PortType::Points2D,
            "Points (at least 3 distinct, not all on one line).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "mesh",
                PortType::Mesh,
                "The triangulation at z = 0, counter-clockwise triangles.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "points, vertices, duplicates_merged, triangles, hull_vertices, area.",
            ),
        ]
    }

    fn new(_: Delaunay2dParams) -> Result<Self, String> {
        Ok(Delaunay2d)
    }
}

impl Operator for Delaunay2d {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let points = match inputs.require("points")? {
            Value::Points2D(p) => p,
            other => {
                return Err(OpError::input(
                    "points",
                    format!("expected Points2D, got {}", other.port_type()),
                ));
            }
        };
        let t = delaunay_2d(points).map_err(|e| OpError::input("points", e.to_string()))?;
        let mesh = Mesh {
            positions: t
                .vertices
                .iter()
                .map(|&i| {
                    let [x, y] = points[i as usize];
                    [x as f32, y as f32, 0.0]
                })
                .collect(),
            triangles: t.triangles.clone(),
            ..Mesh::default()
        };
        let mut m = Metrics::new();
        m.insert("points".into(), points.len() as f64);
        m.insert("vertices".into(), t.vertices.len() as f64);
        m.insert("duplicates_merged".into(), t.duplicates as f64);
        m.insert("triangles".into(), t.triangles.len() as f64);
        m.insert("hull_vertices".into(), t.hull_vertices as f64);
        m.insert("area".into(), t.area);
        Ok(Outputs::new()
            .with("mesh", Value::Mesh(Arc::new(mesh)))
            .with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::brief::SplitMix64;
    use crate::mesh::halfedge::HalfedgeMesh;
    use proptest::prelude::*;

    fn orient(a: [f64; 2], b: [f64; 2], c: [f64; 2]) -> f64 {
        (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    }

    /// Positive when `d` is strictly inside the circumcircle of CCW (a, b, c); computed
    /// relative to `d`.
    fn incircle(a: [f64; 2], b: [f64; 2], c: [f64; 2], d: [f64; 2]) -> f64 {
        let r = |p: [f64; 2]| {
            let (x, y) = (p[0] - d[0], p[1] - d[1]);
            (x, y, x * x + y * y)
        };
        let (ax, ay, a2) = r(a);
        let (bx, by, b2) = r(b);
        let (cx, cy, c2) = r(c);
        ax * (by * c2 - b2 * cy) - ay * (bx * c2 - b2 * cx) + a2 * (bx * cy - by * cx)
    }

    /// Number of points on the boundary of the convex hull (strict corners plus points in the
    /// middle of hull edges), by brute force: p is on the boundary iff some line through p has
    /// every point on one side.
    fn hull_boundary_count(p: &[[f64; 2]]) -> usize {
        (0..p.len())
            .filter(|&i| {
                (0..p.len()).filter(|&j| j != i).any(|j| {
                    let s: Vec<f64> = p.iter().map(|&q| orient(p[i], p[j], q)).collect();
                    s.iter().all(|&x| x >= 0.0) || s.iter().all(|&x| x <= 0.0)
                })
            })
            .count()
    }

    fn check(points: &[[f64; 2]], t: &Triangulation2d) {
        let v: Vec<[f64; 2]> = t.vertices.iter().map(|&i| points[i as usize]).collect();
        let scale = v
            .iter()
            .flatten()
            .fold(0.0f64, |m, &x| m.max(x.abs()))
            .max(1e-300);
        // CCW, non-degenerate.
        for tri in &t.triangles {
            let [a, b, c] = tri.map(|k| v[k as usize]);
            assert!(orient(a, b, c) > 0.0, "{tri:?} not counter-clockwise");
        }
        // Empty circumcircles, by brute force.
        for tri in &t.triangles {
            let [a, b, c] = tri.map(|k| v[k as usize]);
            for (k, &d) in v.iter().enumerate() {
                if tri.contains(&(k as u32)) {
                    continue;
                }
                let s = incircle(a, b, c, d);
                assert!(s <= 1e-9 * scale.powi(4), "point {k} inside {tri:?}: {s}");
            }
        }
        // Triangle count from Euler: 2n − 2 − h.
        let h = hull_boundary_count(&v);
        assert_eq!(t.hull_vertices, h);
        assert_eq!(t.triangles.len(), 2 * v.len() - 2 - h);
        // A single disc, consistently oriented.
        let p3: Vec<[f64; 3]> = v.iter().map(|p| [p[0], p[1], 0.0]).collect();
        let mesh = HalfedgeMesh::from_triangles(p3, &t.triangles).unwrap();
        mesh.validate().unwrap();
        assert_eq!(mesh.euler_characteristic(), 1);
        assert_eq!(mesh.boundary_loops().len(), 1);
    }

    #[test]
    fn square_grid() {
        let k = 7;
        let p: Vec<[f64; 2]> = (0..k * k)
            .map(|i| [(i % k) as f64, (i / k) as f64])
            .collect();
        let t = delaunay_2d(&p).unwrap();
        assert_eq!(t.vertices.len(), k * k);
        assert_eq!(t.triangles.len(), 2 * (k - 1) * (k - 1));
        assert_eq!(t.hull_vertices, 4 * (k - 1));
        assert_eq!(t.area, ((k - 1) * (k - 1)) as f64);
        // Every triangle is half a unit cell: area 1/2, legs 1.
        for tri in &t.triangles {
            let [a, b, c] = tri.map(|i| p[i as usize]);
            assert_eq!(orient(a, b, c), 1.0);
        }
        check(&p, &t);
    }

    #[test]
    fn hand_computed_quad_takes_the_delaunay_diagonal() {
        // A kite: the diagonal 1–3 (short) is Delaunay, 0–2 (long) is not.
        let p = [[-2.0, 0.0], [0.0, -0.5], [2.0, 0.0], [0.0, 0.5]];
        let t = delaunay_2d(&p).unwrap();
        assert_eq!(t.triangles, vec![[0, 1, 3], [1, 2, 3]]);
        assert_eq!(t.hull_vertices, 4);
        assert_eq!(t.area, 2.0);
    }

    #[test]
    fn duplicates_are_merged_and_errors_are_clear() {
        let p = [
            [0.0, 0.0],
            [1.0, 0.0],
            [-0.0, 0.0],
            [0.0, 1.0],
            [1.0, 0.0],
            [1.0, 1.0],
        ];
        let t = delaunay_2d(&p).unwrap();
        assert_eq!(t.vertices, vec![0, 1, 3, 5]);
        assert_eq!(t.duplicates, 2);
        assert_eq!(t.triangles.len(), 2);
        assert_eq!(
            delaunay_2d(&[[0.0, 0.0], [1.0, 1.0], [0.0, 0.0]]),
            Err(DelaunayError::TooFewPoints {
                points: 3,
                distinct: 2
            })
        );
        assert!(matches!(
            delaunay_2d(&[]),
            Err(DelaunayError::TooFewPoints { .. })
        ));
        let line: Vec<[f64; 2]> = (0..20).map(|i| [i as f64 * 0.5, 3.0 - i as f64]).collect();
        assert_eq!(delaunay_2d(&line), Err(DelaunayError::Collinear(20)));
        assert_eq!(
            delaunay_2d(&[[0.0, 0.0], [1.0, f64::NAN], [0.0, 1.0]]),
            Err(DelaunayError::NonFinite { index: 1 })
        );
        assert_eq!(
            delaunay_2d(&[[0.0, 0.0], [1.0, 0.0], [f64::INFINITY, 1.0]]),
            Err(DelaunayError::NonFinite { index: 2 })
        );
    }

    #[test]
    fn large_offset_and_determinism() {
        let mut rng = SplitMix64::new(11);
        let p: Vec<[f64; 2]> = (0..300)
            .map(|_| [1e6 + rng.uniform(), -3e6 + rng.uniform()])
            .collect();
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| delaunay_2d(&p).unwrap())
        };
        let a = run(1);
        assert_eq!(a, run(4));
        // Check relative to the offset (the brute-force predicates are not exact).
        let local: Vec<[f64; 2]> = p.iter().map(|q| [q[0] - 1e6, q[1] + 3e6]).collect();
        assert_eq!(delaunay_2d(&local).unwrap().triangles, a.triangles);
        check(&local, &a);
    }

    #[test]
    fn op_outputs_a_flat_ccw_mesh() {
        let op = Delaunay2d::new(Delaunay2dParams::default()).unwrap();
        let specs = Delaunay2d::inputs();
        let pts = vec![[0.0, 0.0], [2.0, 0.0], [0.0, 2.0], [2.0, 2.0], [1.0, 0.9]];
        let values = [Some(Value::Points2D(Arc::new(pts)))];
        let ctx = RunContext {
            node: "tri".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Mesh(m)) = out.take("mesh") else {
            panic!("no mesh")
        };
        assert_eq!(m.positions.len(), 5);
        assert_eq!(m.triangles.len(), 4);
        assert!(m.positions.iter().all(|p| p[2] == 0.0));
        let Some(Value::Metrics(metrics)) = out.take("metrics") else {
            panic!("no metrics")
        };
        assert_eq!(metrics["area"], 4.0);
        assert_eq!(metrics["hull_vertices"], 4.0);
        let values = [Some(Value::Points2D(Arc::new(vec![
            [0.0, 0.0],
            [1.0, 1.0],
        ])))];
        let e = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap_err();
        assert!(e.to_string().contains("at least 3"), "{e}");
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        /// Random points (uniform, clustered, on a coarse lattice with duplicates): CCW
        /// triangles, empty circumcircles, 2n − 2 − h triangles, one disc.
        #[test]
        fn empty_circumcircles(seed in 0u64..1_000_000, n in 3usize..80, kind in 0u8..3) {
            let mut rng = SplitMix64::new(seed);
            let p: Vec<[f64; 2]> = (0..n)
                .map(|_| match kind {
                    0 => [rng.uniform(), rng.uniform()],
                    1 => [1e-3 * rng.uniform(), 1e3 * rng.uniform()],
                    _ => [(rng.uniform() * 6.0).floor(), (rng.uniform() * 6.0).floor()],
                })
                .collect();
            match delaunay_2d(&p) {
                Ok(t) => {
                    prop_assert_eq!(t.vertices.len() + t.duplicates, n);
                    check(&p, &t);
                }
                Err(DelaunayError::Collinear(_)) | Err(DelaunayError::TooFewPoints { .. }) => {
                    prop_assert!(kind == 2 || n < 4);
                }
                Err(e) => prop_assert!(false, "{e}"),
            }
        }
    }
}
