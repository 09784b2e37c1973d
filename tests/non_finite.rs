//! The NaN/Inf policy (RELIABILITY.md): a non-finite geometric value never reaches an operator
//! that has not declared it accepts one. A statically linked test operator emits 2-D points with
//! a NaN (as a buggy plugin could); the robust homography estimator downstream must not run on
//! them, and the run's failure names the node, the port and the element. An operator whose
//! port opts in (`PortSpec::accepts_non_finite`) still receives them.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

use std::sync::Arc;

use ocellus_engine::diag::SourceFile;
use ocellus_engine::resolve::load_source;
use ocellus_engine::{
    Inputs, NoParams, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, RunOptions,
    Value,
};

/// Eight points on a grid, the fourth `(NaN, y)` when `BAD`.
struct GridPoints<const BAD: bool>;

impl<const BAD: bool> Operator for GridPoints<BAD> {
    fn run(&self, _: &RunContext, _: &Inputs<'_>) -> Result<Outputs, OpError> {
        let mut points: Vec<[f64; 2]> = (0..8)
            .map(|i| {
                [
                    f64::from(i % 4) * 50.0 + 10.0,
                    f64::from(i / 4) * 70.0 + 5.0 + f64::from(i),
                ]
            })
            .collect();
        if BAD {
            points[3][0] = f64::NAN;
        }
        Ok(Outputs::new().with("points", Value::Points2D(Arc::new(points))))
    }
}

impl<const BAD: bool> Op for GridPoints<BAD> {
    type Params = NoParams;
    const ID: &'static str = if BAD {
        "test.bad_points"
    } else {
        "test.good_points"
    };
    const SUMMARY: &'static str = "Grid points.";
    const DOC: &'static str = "Eight grid points.";
    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }
    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("points", PortType::Points2D, "points")]
    }
    fn new(_: NoParams) -> Result<Self, String> {
        Ok(GridPoints)
    }
}

/// Counts the NaN coordinates it is given: an operator that accepts them.
struct CountNan;

impl Operator for CountNan {
    fn run(&self, _: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let Some(Value::Points2D(p)) = inputs.get("points") else {
            return Err(OpError::input("points", "missing"));
        };
        let n = p.iter().flatten().filter(|x| x.is_nan()).count();
        Ok(Outputs::new().with("count", Value::Integer(n as i64)))
    }
}

impl Op for CountNan {
    type Params = NoParams;
    const ID: &'static str = "test.count_nan";
    const SUMMARY: &'static str = "Counts NaN coordinates.";
    const DOC: &'static str = "Counts NaN coordinates.";
    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("points", PortType::Points2D, "points").accepts_non_finite()]
    }
    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("count", PortType::Integer, "count")]
    }
    fn new(_: NoParams) -> Result<Self, String> {
        Ok(CountNan)
    }
}

fn run(text: &str) -> ocellus_engine::RunReport {
    let mut registry = ocellus_nodes::builtin_registry().unwrap();
    registry.register::<GridPoints<false>>().unwrap();
    registry.register::<GridPoints<true>>().unwrap();
    registry.register::<CountNan>().unwrap();
    let source = SourceFile::new("nan.ron", None, text.to_string());
    let graph = load_source(&registry, &source, &[]).unwrap();
    ocellus_engine::run(&graph, &RunOptions::default()).unwrap()
}

const GRAPH: &str = r#"(
    nodes: {
        "left": (op: "test.good_points"),
        "right": (op: "RIGHT"),
        "fit": (op: "geometry.find_homography",
                inputs: { "points_left": "left.points", "points_right": "right.points" }),
        "count": (op: "test.count_nan", inputs: { "points": "right.points" }),
    },
    outputs: { "H": "fit.H", "count": "count.count" },
)"#;

#[test]
fn a_nan_point_stops_the_estimator_naming_node_port_and_element() {
    let report = run(&GRAPH.replace("RIGHT", "test.bad_points"));
    let failures: Vec<String> = report.failures.iter().map(ToString::to_string).collect();
    assert_eq!(failures.len(), 1, "{failures:?}");
    let message = &failures[0];
    for needle in ["fit", "points_right", "point 3", "not finite"] {
        assert!(
            message.contains(needle),
            "`{needle}` missing from: {message}"
        );
    }
    // The operator that accepts them ran and saw the NaN.
    let count = report.outputs.iter().find(|(name, _)| name == "count");
    assert_eq!(count.map(|(_, v)| v), Some(&Value::Integer(1)));
}

#[test]
fn finite_points_pass_the_same_check() {
    let report = run(&GRAPH.replace("RIGHT", "test.good_points"));
    assert!(report.failures.is_empty(), "{:?}", report.failures);
}

/// A 6 × 2 track with a missing (NaN) third row, as a detector reports a missed frame.
struct Measurements;

impl Operator for Measurements {
    fn run(&self, _: &RunContext, _: &Inputs<'_>) -> Result<Outputs, OpError> {
        let mut data: Vec<f64> = (0..6)
            .flat_map(|t| [10.0 + 3.0 * f64::from(t), 20.0])
            .collect();
        data[4] = f64::NAN;
        data[5] = f64::NAN;
        let m = ocellus_engine::value::Matrix::new(6, 2, data).unwrap();
        Ok(Outputs::new().with("m", Value::Matrix(Arc::new(m))))
    }
}

impl Op for Measurements {
    type Params = NoParams;
    const ID: &'static str = "test.measurements";
    const SUMMARY: &'static str = "A track with a gap.";
    const DOC: &'static str = "A track with a gap.";
    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }
    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("m", PortType::Matrix, "measurements")]
    }
    fn new(_: NoParams) -> Result<Self, String> {
        Ok(Measurements)
    }
}

/// Matrices are not geometric values: NaN marks a missing measurement, and the Kalman filter
/// (whose documented input this is) runs through the scheduler and bridges the gap.
#[test]
fn a_matrix_with_missing_rows_reaches_the_kalman_filter() {
    let mut registry = ocellus_nodes::builtin_registry().unwrap();
    registry.register::<Measurements>().unwrap();
    let text = r#"(
        nodes: {
            "track": (op: "test.measurements"),
            "kf": (op: "video.kalman_filter", inputs: { "measurements": "track.m" }),
        },
        outputs: { "positions": "kf.positions" },
    )"#;
    let source = SourceFile::new("kalman.ron", None, text.to_string());
    let graph = load_source(&registry, &source, &[]).unwrap();
    let report = ocellus_engine::run(&graph, &RunOptions::default()).unwrap();
    assert!(report.failures.is_empty(), "{:?}", report.failures);
    let Some((_, Value::Matrix(positions))) = report.outputs.iter().find(|(n, _)| n == "positions")
    else {
        panic!("no positions");
    };
    // The missing frame is estimated, not left NaN.
    assert!(positions.data[4].is_finite() && positions.data[5].is_finite());
}
