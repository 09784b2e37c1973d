//! `io.read_bal`: read a "Bundle Adjustment in the Large" (BAL) problem into a reconstruction.
//!
//! BAL text format (Agarwal et al., ECCV 2010): a header `num_cameras num_points
//! num_observations`, then one `camera point x y` line per observation, then 9 numbers per
//! camera (angle-axis `r`, `t`, `f`, `k1`, `k2`) and 3 per point, whitespace separated. BAL's
//! model: `P = R(r) X + t`, `p = −P.xy / P.z`, pixel `f (1 + k1 |p|² + k2 |p|⁴) p`, principal
//! point 0, image y up.
//!
//! The reconstruction holds it exactly in COLMAP's conventions (camera looking along +z, image
//! y down): BAL camera `i` becomes a `RADIAL` camera `[f, 0, 0, k1, k2]` and image `i + 1` with
//! `camera_from_world = (D R, D t)`, `D = diag(1, −1, −1)`, and each observation `(x, y)`
//! becomes the 2-D point `(x, −y)`. Then `D P` projects to `(−P.x/P.z, P.y/P.z)`, BAL's `p` with
//! y negated, so every residual is BAL's with its y component negated and the cost ½Σr² is
//! identical. Points behind their camera keep their residual (no cheirality test anywhere).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use ocellus_engine::value::Reconstruction;
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value,
};

use crate::geometry::camera::{angle_axis, rodrigues, to_na};
use crate::optimize::ba::{BaCamera, BaObservation, BaProblem};
use crate::optimize::bundle_adjust::problem_to_reconstruction;

/// Most cameras in a BAL file.
pub const MAX_CAMERAS: usize = 1_000_000;
/// Most points in a BAL file.
pub const MAX_POINTS: usize = 100_000_000;
/// Most observations in a BAL file.
pub const MAX_OBSERVATIONS: usize = 500_000_000;

/// A parsed BAL file, in BAL's own conventions.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BalFile {
    /// Per camera `[r0, r1, r2, t0, t1, t2, f, k1, k2]`.
    pub cameras: Vec<[f64; 9]>,
    /// Points.
    pub points: Vec<[f64; 3]>,
    /// `(camera, point, [x, y])`.
    pub observations: Vec<(u32, u32, [f64; 2])>,
}

/// Whitespace tokens with their 1-based line numbers.
struct Tokens<'a> {
    lines: std::iter::Enumerate<std::str::Lines<'a>>,
    current: std::str::SplitWhitespace<'a>,
    line: usize,
}

impl<'a> Tokens<'a> {
    fn new(text: &'a str) -> Tokens<'a> {
        Tokens {
            lines: text.lines().enumerate(),
            current: "".split_whitespace(),
            line: 0,
        }
    }

    fn next(&mut self, what: &dyn Fn() -> String) -> Result<(&'a str, usize), String> {
        loop {
            if let Some(t) = self.current.next() {
                return Ok((t, self.line));
            }
            match self.lines.next() {
                Some((i, l)) => {
                    self.line = i + 1;
                    self.current = l.split_whitespace();
                }
                None => return Err(format!("unexpected end of file: expected {}", what())),
            }
        }
    }

    fn float(&mut self, what: &dyn Fn() -> String) -> Result<f64, String> {
        let (t, line) = self.next(what)?;
        let v: f64 = t
            .parse()
            .map_err(|_| format!("line {line}: {} `{t}` is not a number", what()))?;
        if !v.is_finite() {
            return Err(format!("line {line}: {} `{t}` is not finite", what()));
        }
        Ok(v)
    }

    fn index(&mut self, what: &dyn Fn() -> String, limit: usize) -> Result<usize, String> {
        let (t, line) = self.next(what)?;
        let v: usize = t.parse().map_err(|_| {
            format!(
                "line {line}: {} `{t}` is not a non-negative integer",
                what()
            )
        })?;
        if v >= limit {
            return Err(format!(
                "line {line}: {} {v} is out of range (must be below {limit})",
                what()
            ));
        }
        Ok(v)
    }
}

/// Parses BAL text. Errors name the 1-based line.
pub fn parse_bal(text: &str) -> Result<BalFile, String> {
    let mut tok = Tokens::new(text);
    let n_cams = tok.index(&|| "the number of cameras".into(), MAX_CAMERAS + 1)?;
    let n_pts = tok.index(&|| "the number of points".into(), MAX_POINTS + 1)?;
    let n_obs = tok.index(
        &|| "the number of observations".into(),
        MAX_OBSERVATIONS + 1,
    )?;
    // Every number takes at least one byte and a separator: do not trust a header that
    // promises more (it would only make us allocate).
    for (what, n) in [
        ("cameras", n_cams),
        ("points", n_pts),
        ("observations", n_obs),
    ] {
        ocellus_engine::limits::check_count(what, n as u64).map_err(|e| format!("line 1: {e}"))?;
    }
    let needed = 4 * n_obs + 9 * n_cams + 3 * n_pts;
    if needed > text.len() {
        return Err(format!(
            "line 1: the header promises {n_cams} cameras, {n_pts} points and {n_obs} \
             observations, more than the file's {} bytes can hold",
            text.len()
        ));
    }
    let mut file = BalFile {
        cameras: Vec::with_capacity(n_cams),
        points: Vec::with_capacity(n_pts),
        observations: Vec::with_capacity(n_obs),
    };
    for k in 0..n_obs {
        let c = tok.index(&|| format!("camera index of observation {k}"), n_cams)?;
        let p = tok.index(&|| format!("point index of observation {k}"), n_pts)?;
        let x = tok.float(&|| format!("x of observation {k}"))?;
        let y = tok.float(&|| format!("y of observation {k}"))?;
        file.observations.push((c as u32, p as u32, [x, y]));
    }
    for c in 0..n_cams {
        let mut cam = [0.0; 9];
        for (i, v) in cam.iter_mut().enumerate() {
            *v = tok.float(&|| format!("parameter {i} of camera {c}"))?;
        }
        file.cameras.push(cam);
    }
    for p in 0..n_pts {
        let mut x = [0.0; 3];
        for (i, v) in x.iter_mut().enumerate() {
            *v = tok.float(&|| format!("coordinate {i} of point {p}"))?;
        }
        file.points.push(x);
    }
    if let Ok((t, line)) = tok.next(&String::new) {
        return Err(format!(
            "line {line}: unexpected `{t}` after the last point"
        ));
    }
    Ok(file)
}

/// `D = diag(1, −1, −1)` applied to a row-major rotation's rows.
fn flip_rows(r: &[f64; 9]) -> [f64; 9] {
    std::array::from_fn(|k| if k < 3 { r[k] } else { -r[k] })
}

/// The BAL file as a problem in COLMAP's conventions (see the module documentation).
pub fn bal_to_problem(file: &BalFile) -> BaProblem {
    let cameras = file
        .cameras
        .iter()
        .map(|c| {
            let r = rodrigues([c[0], c[1], c[2]]);
            let r: [f64; 9] = std::array::from_fn(|k| r[(k / 3, k % 3)]);
            BaCamera {
                rotation: flip_rows(&r),
                translation: [c[3], -c[4], -c[5]],
                intrinsics: [c[6], c[7], c[8]],
                principal_point: [0.0, 0.0],
            }
        })
        .collect();
    let observations = file
        .observations
        .iter()
        .map(|&(c, p, [x, y])| BaObservation {
            camera: c,
            point: p,
            xy: [x, -y],
        })
        .collect();
    BaProblem {
        cameras,
        points: file.points.clone(),
        observations,
        ..BaProblem::default()
    }
}

/// The BAL file as a reconstruction (see the module documentation); the cameras' image size is
/// twice the largest |coordinate| of the observations, rounded up, plus 2.
pub fn bal_to_reconstruction(file: &BalFile) -> Reconstruction {
    let extent = file
        .observations
        .iter()
        .fold(0.0f64, |m, o| m.max(o.2[0].abs()).max(o.2[1].abs()));
    let side = (2.0 * (extent.ceil() + 1.0)).min(u32::MAX as f64) as u32;
    problem_to_reconstruction(&bal_to_problem(file), [side, side])
}

/// BAL text of a problem in COLMAP's conventions (the inverse of [`bal_to_problem`]); errors if
/// a camera's principal point is not 0. Numbers are written in Rust's shortest round-trip form.
pub fn write_bal(problem: &BaProblem) -> Result<String, String> {
    use std::fmt::Write as _;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{} {} {}",
        problem.cameras.len(),
        problem.points.len(),
        problem.observations.len()
    );
    for o in &problem.observations {
        let _ = writeln!(s, "{} {} {:e} {:e}", o.camera, o.point, o.xy[0], -o.xy[1]);
    }
    for (i, c) in problem.cameras.iter().enumerate() {
        if c.principal_point != [0.0, 0.0] {
            return Err(format!("camera {i}: BAL cameras have principal point 0"));
        }
        let r = flip_rows(&c.rotation);
        let w = angle_axis(&to_na(&r));
        let t = [c.translation[0], -c.translation[1], -c.translation[2]];
        for v in w.iter().chain(&t).chain(&c.intrinsics) {
            let _ = writeln!(s, "{v:e}");
        }
    }
    for p in &problem.points {
        for v in p {
            let _ = writeln!(s, "{v:e}");
        }
    }
    Ok(s)
}

ocellus_engine::params! {
    /// Parameters of [`ReadBal`].
    pub struct ReadBalParams {
        /// The BAL text file; relative paths resolve against the graph file's folder.
        path: PathBuf = PathBuf::new(),
    }
}

/// Reads and parses a BAL file.
pub fn read_bal(path: &Path) -> Result<BalFile, OpError> {
    let text = ocellus_engine::limits::read_text(path).map_err(|e| OpError::io(path, e))?;
    parse_bal(&text).map_err(|e| OpError::failed(format!("{}: {e}", path.display())))
}

/// `io.read_bal`. See [`parse_bal`] and [`bal_to_reconstruction`].
pub struct ReadBal {
    params: ReadBalParams,
}

impl Op for ReadBal {
    type Params = ReadBalParams;
    const ID: &'static str = "io.read_bal";
    const SUMMARY: &'static str =
        "Read a Bundle Adjustment in the Large (BAL) problem into a reconstruction.";
    const DOC: &'static str = r#"
Reads a BAL problem file (Agarwal, Snavely, Seitz & Szeliski, "Bundle adjustment in the large",
ECCV 2010): header `cameras points observations`, one `camera point x y` per observation, then 9
numbers per camera (angle-axis r, t, f, k1, k2) and 3 per point. BAL's camera:
P = R(r)·X + t, p = −P.xy/P.z, pixel f·(1 + k1|p|² + k2|p|⁴)·p, principal point 0, y up.

The output reconstruction holds the problem exactly in COLMAP's conventions: BAL camera i is a
RADIAL camera [f, 0, 0, k1, k2] and image i + 1 with camera_from_world = (D·R, D·t),
D = diag(1, −1, −1); observation (x, y) becomes the 2-D point (x, −y); point j gets id j. The
reprojection residuals are BAL's with y negated, so the cost ½Σr² is BAL's (Ceres' convention),
including points behind their cameras.

Malformed files are errors naming the line: wrong token counts, non-numbers, NaN/Inf, indices
out of range, trailing data, headers larger than the file can hold; at most 10⁶ cameras,
10⁸ points and 5·10⁸ observations.

Example:
    "problem": (op: "io.read_bal", params: (path: "data/bal_small.txt")),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "reconstruction",
            PortType::Reconstruction,
            "The problem: one RADIAL camera and image per BAL camera, points with ids 0..n.",
        )]
    }

    fn new(params: ReadBalParams) -> Result<Self, String> {
        if params.path.as_os_str().is_empty() {
            return Err("`path` is required".into());
        }
        Ok(ReadBal { params })
    }
}

impl Operator for ReadBal {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let file = read_bal(&self.params.path)?;
        Ok(Outputs::new().with(
            "reconstruction",
            Value::Reconstruction(Arc::new(bal_to_reconstruction(&file))),
        ))
    }

    /// The file's contents decide the result, so they are part of the cache key.
    fn fingerprint(&self) -> Result<Vec<u8>, OpError> {
        let bytes = ocellus_engine::limits::read_file(&self.params.path)
            .map_err(|e| OpError::io(&self.params.path, e))?;
        Ok(ocellus_engine::cache::content_hash(&bytes).to_vec())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optimize::ba::problem_cost;
    use crate::optimize::loss::RobustLoss;
    use crate::optimize::synthetic::{SyntheticOptions, synthetic_problem};

    /// BAL's own cost, computed in BAL's conventions.
    fn bal_cost(file: &BalFile) -> f64 {
        let mut sum = 0.0;
        for &(c, p, obs) in &file.observations {
            let cam = &file.cameras[c as usize];
            let r = rodrigues([cam[0], cam[1], cam[2]]);
            let x = &file.points[p as usize];
            let pt: [f64; 3] = std::array::from_fn(|i| {
                r[(i, 0)] * x[0] + r[(i, 1)] * x[1] + r[(i, 2)] * x[2] + cam[3 + i]
            });
            let q = [-pt[0] / pt[2], -pt[1] / pt[2]];
            let r2 = q[0] * q[0] + q[1] * q[1];
            let d = cam[6] * (1.0 + cam[7] * r2 + cam[8] * r2 * r2);
            let (dx, dy) = (d * q[0] - obs[0], d * q[1] - obs[1]);
            sum += dx * dx + dy * dy;
        }
        0.5 * sum
    }

    const TINY: &str = "2 2 3\n0 0 -3.2 1.5\n1 0 2.0 -1.0\n1 1 0.5 0.25\n\
        0.01 -0.02 0.03 0.1 0.2 -5.0 400 -0.1 0.01\n\
        -0.02 0.01 0.0 -0.3 0.1 -4.0 420 0.05 0.0\n\
        0.1 0.2 0.3\n-0.5 0.4 1.0\n";

    #[test]
    fn parses_and_keeps_bal_cost() {
        let file = parse_bal(TINY).unwrap();
        assert_eq!(file.cameras.len(), 2);
        assert_eq!(file.points[1], [-0.5, 0.4, 1.0]);
        assert_eq!(file.observations[0], (0, 0, [-3.2, 1.5]));
        let ours = problem_cost(&bal_to_problem(&file), RobustLoss::Trivial).unwrap();
        let theirs = bal_cost(&file);
        assert!(theirs > 1.0);
        assert!(
            (ours - theirs).abs() <= 1e-12 * theirs,
            "{ours} vs {theirs}"
        );
        let rec = bal_to_reconstruction(&file);
        assert_eq!(rec.images.len(), 2);
        assert_eq!(rec.images[1].points2d[1], ([0.5, -0.25], Some(1)));
        assert_eq!(rec.cameras[&1].params, vec![400.0, 0.0, 0.0, -0.1, 0.01]);
    }

    #[test]
    fn points_behind_the_camera_keep_their_residual() {
        // Camera 0 looks along −z (BAL); a point at z = +10 in its frame is behind it.
        let text = "1 1 1\n0 0 1.0 2.0\n0 0 0 0 0 10 100 0 0\n0 0 0\n";
        let file = parse_bal(text).unwrap();
        let ours = problem_cost(&bal_to_problem(&file), RobustLoss::Trivial).unwrap();
        // P = (0, 0, 10): p = (0, 0), residual (−1, −2): cost 2.5.
        assert_eq!(ours, 2.5);
        assert_eq!(bal_cost(&file), 2.5);
    }

    #[test]
    fn write_then_parse_round_trips() {
        let (_, start) = synthetic_problem(&SyntheticOptions {
            cameras: 3,
            points: 20,
            ..SyntheticOptions::default()
        })
        .unwrap();
        let text = write_bal(&start).unwrap();
        let file = parse_bal(&text).unwrap();
        let back = bal_to_problem(&file);
        assert_eq!(back.observations, start.observations);
        assert_eq!(back.points, start.points);
        for (a, b) in back.cameras.iter().zip(&start.cameras) {
            for (x, y) in a.rotation.iter().zip(&b.rotation) {
                assert!((x - y).abs() < 1e-14);
            }
            assert_eq!(a.translation, b.translation);
            assert_eq!(a.intrinsics, b.intrinsics);
        }
        let (ca, cb) = (
            problem_cost(&back, RobustLoss::Trivial).unwrap(),
            problem_cost(&start, RobustLoss::Trivial).unwrap(),
        );
        assert!((ca - cb).abs() <= 1e-9 * cb);
    }

    #[test]
    fn malformed_files_name_the_line() {
        let cases = [
            ("", "end of file"),
            ("2 2", "end of file"),
            ("x 1 1", "line 1: the number of cameras `x`"),
            ("1 1 1\n0 0 1.0 2.0\n0 0 0 0 0 10 100 0\n", "end of file"),
            (
                "1 1 1\n0 3 1.0 2.0\n",
                "line 2: point index of observation 0 3 is out of range",
            ),
            (
                "1 1 1\n0 0 1.0 nan\n",
                "line 2: y of observation 0 `nan` is not finite",
            ),
            (
                "1 1 1\n0 0 1.0 2.0\n0 0 0 0 0 10 100 0 0\n0 0 0\n7\n",
                "line 5: unexpected `7`",
            ),
            (
                "1 1 1\n-1 0 1.0 2.0\n",
                "line 2: camera index of observation 0 `-1`",
            ),
            ("1000000 0 0\n", "line 1: the header promises"),
            ("2000000 0 0\n", "out of range"),
        ];
        for (text, expected) in cases {
            let err = parse_bal(text).unwrap_err();
            assert!(err.contains(expected), "{text:?}: {err}");
        }
    }

    #[test]
    fn op_requires_a_path() {
        assert!(ReadBal::new(ReadBalParams::default()).is_err());
    }
}
