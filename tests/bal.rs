//! The BAL example: its fixture `graphs/data/bal_small.txt` is reproduced by the generator
//! below, and bundle adjustment of it reaches the cost of the true scene.
//!
//! To regenerate the fixture after changing the generator, run this test with
//! `OCELLUS_WRITE_FIXTURES=1`.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::root;
use ocellus_nodes::io::read_bal::{bal_to_problem, parse_bal, write_bal};
use ocellus_nodes::optimize::ba::{BaOptions, BaProblem, problem_cost, solve};
use ocellus_nodes::optimize::loss::RobustLoss;
use ocellus_nodes::optimize::synthetic::{SyntheticOptions, synthetic_problem};

/// The generated problem of `graphs/bal.ron`: (truth, start).
fn fixture_problem() -> (BaProblem, BaProblem) {
    synthetic_problem(&SyntheticOptions {
        cameras: 8,
        points: 150,
        noise_px: 0.5,
        seed: 2024,
        ..SyntheticOptions::default()
    })
    .unwrap()
}

#[test]
fn bal_fixture_is_reproducible() {
    let (_, start) = fixture_problem();
    let text = write_bal(&start).unwrap();
    let path = root().join("graphs/data/bal_small.txt");
    if std::env::var_os("OCELLUS_WRITE_FIXTURES").is_some() {
        std::fs::write(&path, &text).unwrap();
    }
    let stored = std::fs::read_to_string(&path).unwrap();
    assert!(stored.len() < 200_000);
    assert!(
        stored == text,
        "graphs/data/bal_small.txt differs from the generator"
    );
}

#[test]
fn bal_fixture_adjusts_to_the_true_cost() {
    let (truth, _) = fixture_problem();
    let stored = std::fs::read_to_string(root().join("graphs/data/bal_small.txt")).unwrap();
    let mut problem = bal_to_problem(&parse_bal(&stored).unwrap());
    let true_cost = problem_cost(&truth, RobustLoss::Trivial).unwrap();
    let summary = solve(&mut problem, &BaOptions::default()).unwrap();
    assert!(summary.initial_cost > 10.0 * true_cost);
    assert!(
        summary.final_cost <= true_cost,
        "{} > {true_cost}",
        summary.final_cost
    );
    assert!(summary.final_cost > 0.5 * true_cost);
}
