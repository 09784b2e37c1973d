//! Bundle adjustment of a BAL file with Ceres-like settings; prints costs, iterations and time.
//!
//!     cargo run --release -p ocellus-nodes --example bal -- FILE
//!         [--solver auto|dense|sparse|iterative] [--ftol 1e-6] [--gtol 1e-4] [--ptol 0]
//!         [--max-iterations 100] [--huber SCALE] [--history]
//!
//! `FILE` may instead be `--synthetic CAMERAS POINTS VISIBILITY`: the generated problem of
//! `optimize::synthetic::synthetic_problem` (seed 1, its other defaults; each point is seen by
//! about `VISIBILITY` × CAMERAS cameras), started from its perturbed start.

use std::time::Instant;

use ocellus_nodes::io::read_bal::{bal_to_problem, parse_bal};
use ocellus_nodes::optimize::ba::{BaOptions, LinearSolver, problem_cost, solve};
use ocellus_nodes::optimize::loss::RobustLoss;
use ocellus_nodes::optimize::synthetic::{SyntheticOptions, synthetic_problem};

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage = "usage: bal FILE|--synthetic CAMERAS POINTS VISIBILITY [options]";
    let path = args.first().ok_or(usage)?;
    let synthetic = if path == "--synthetic" {
        let field = |k: usize| args.get(k).ok_or(usage.to_string());
        let count =
            |k: usize| -> Result<usize, String> { field(k)?.parse().map_err(|e| format!("{e}")) };
        Some(SyntheticOptions {
            cameras: count(1)?,
            points: count(2)?,
            visibility: field(3)?.parse().map_err(|e| format!("{e}"))?,
            ..SyntheticOptions::default()
        })
    } else {
        None
    };
    let mut options = BaOptions {
        max_iterations: 100,
        gradient_tolerance: 1e-4,
        parameter_tolerance: 0.0,
        ..BaOptions::default()
    };
    let mut history = false;
    let mut i = if synthetic.is_some() { 4 } else { 1 };
    while i < args.len() {
        let value = || args.get(i + 1).cloned().ok_or("missing value".to_string());
        let number = || -> Result<f64, String> { value()?.parse().map_err(|e| format!("{e}")) };
        match args[i].as_str() {
            "--solver" => {
                options.linear_solver = match value()?.as_str() {
                    "auto" => LinearSolver::Auto,
                    "dense" => LinearSolver::DenseSchur,
                    "sparse" => LinearSolver::SparseSchur,
                    "iterative" => LinearSolver::IterativeSchur,
                    s => return Err(format!("unknown solver {s}")),
                };
                i += 1;
            }
            "--ftol" => {
                options.function_tolerance = number()?;
                i += 1;
            }
            "--gtol" => {
                options.gradient_tolerance = number()?;
                i += 1;
            }
            "--ptol" => {
                options.parameter_tolerance = number()?;
                i += 1;
            }
            "--max-iterations" => {
                options.max_iterations = number()? as usize;
                i += 1;
            }
            "--huber" => {
                options.loss = RobustLoss::Huber(number()?);
                i += 1;
            }
            "--history" => history = true,
            a => return Err(format!("unknown argument {a}")),
        }
        i += 1;
    }
    let t0 = Instant::now();
    let mut problem = match &synthetic {
        Some(o) => synthetic_problem(o)?.1,
        None => {
            let text = std::fs::read_to_string(path).map_err(|e| e.to_string())?;
            bal_to_problem(&parse_bal(&text)?)
        }
    };
    let t_read = t0.elapsed().as_secs_f64();
    let summary = solve(&mut problem, &options)?;
    let total = t0.elapsed().as_secs_f64();
    let check = problem_cost(&problem, options.loss)?;
    let n = problem.observations.len() as f64;
    println!(
        "{path}: cameras {} points {} observations {}",
        problem.cameras.len(),
        problem.points.len(),
        problem.observations.len()
    );
    println!(
        "initial_cost {:.6e} final_cost {:.6e} (recomputed {:.6e}) iterations {} (successful {}, unsuccessful {}) termination {:?} solver {:?}",
        summary.initial_cost,
        summary.final_cost,
        check,
        summary.iterations,
        summary.successful_steps,
        summary.unsuccessful_steps,
        summary.termination,
        summary.linear_solver
    );
    println!(
        "rms {:.4} px; read {:.3} s, solve {:.3} s ({:.1} ms per iteration), total {:.3} s",
        (2.0 * summary.final_cost / n).sqrt(),
        t_read,
        summary.time_s,
        1e3 * summary.time_s / summary.iterations.max(1) as f64,
        total
    );
    if history {
        for (k, h) in summary.history.iter().enumerate() {
            println!(
                "{k:3} cost {:.6e} step {:.3e} radius {:.3e} accepted {} t {:.3} cg {}",
                h.cost, h.step_norm, h.radius, h.accepted, h.time_s, h.cg_iterations
            );
        }
    }
    Ok(())
}
