//! `ocellus sweep` end to end: the grid, the files it writes, and a Pareto front that trades
//! time for accuracy on the homography graph (the README's example).

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

use std::path::PathBuf;
use std::process::Command;

fn out_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("ocellus-sweep-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn ocellus(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_ocellus"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(args)
        .output()
        .unwrap()
}

/// Plain RANSAC on the unfiltered matches (a quarter of them inliers): few trials miss the
/// homography, enough trials find it. Along the front time rises and the error falls, and the
/// cheapest accurate setting needs hundreds of trials.
#[test]
fn ransac_trials_trade_time_for_accuracy() {
    let dir = out_dir("ransac");
    let out = ocellus(&[
        "sweep",
        "graphs/homography.ron",
        "--set",
        "match.ratio=1.0",
        "--set",
        "ransac.method=ransac",
        "--vary",
        "ransac.max_trials=2,20,200,2000",
        "--vary",
        "ransac.threshold_px=1,3",
        "--metric",
        "error.corner_error_px",
        "--metric",
        "inliers:max",
        "--repeat",
        "2",
        "--threads",
        "2",
        "--out",
        dir.to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let csv = std::fs::read_to_string(dir.join("sweep.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next().unwrap(),
        "ransac.max_trials,ransac.threshold_px,time_ms,wall_ms,error.corner_error_px,inliers,pareto:error.corner_error_px,pareto:inliers,problem"
    );
    let rows: Vec<Vec<String>> = lines
        .map(|l| l.split(',').map(str::to_string).collect())
        .collect();
    assert_eq!(rows.len(), 8, "{csv}");
    // The first --vary changes slowest.
    let settings: Vec<(&str, &str)> = rows
        .iter()
        .map(|r| (r[0].as_str(), r[1].as_str()))
        .collect();
    assert_eq!(settings[..3], [("2", "1"), ("2", "3"), ("20", "1")]);
    let num = |r: &Vec<String>, k: usize| r[k].parse::<f64>().unwrap();
    // A setting without a result (its `problem` column says why) has no error.
    let has_result = |r: &Vec<String>| r[8].is_empty();
    let error = |trials: &str, threshold: &str| {
        let r = rows
            .iter()
            .find(|r| r[0] == trials && r[1] == threshold)
            .unwrap();
        if has_result(r) {
            num(r, 4)
        } else {
            f64::INFINITY
        }
    };
    // Only the smallest budget may fail outright (both of its samples degenerate).
    for r in rows.iter().filter(|r| !has_result(r)) {
        assert_eq!(r[0], "2", "{csv}");
        assert!(r[8].contains("degenerate"), "{csv}");
    }
    // Two trials at 25 % inliers almost never draw four inliers; 2000 always do.
    assert!(error("2", "3") > 100.0, "{csv}");
    assert!(error("2000", "3") < 1.0, "{csv}");
    // The error front, by time: time rises, error falls, and it ends accurate.
    let mut front: Vec<(f64, f64)> = rows
        .iter()
        .filter(|r| r[6] == "1")
        .map(|r| (num(r, 2), num(r, 4)))
        .collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    assert!(front.len() >= 2, "{csv}");
    for w in front.windows(2) {
        assert!(w[1].0 >= w[0].0 && w[1].1 < w[0].1, "{front:?}");
    }
    assert!(front.last().unwrap().1 < 1.0, "{front:?}");
    // Every row off the front is dominated by a front row.
    for r in rows.iter().filter(|r| r[6] == "0" && has_result(r)) {
        let (t, e) = (num(r, 2), num(r, 4));
        assert!(
            front.iter().any(|&(ft, fe)| ft <= t && fe <= e),
            "{r:?} vs {front:?}"
        );
    }
    let md = std::fs::read_to_string(dir.join("sweep.md")).unwrap();
    assert!(
        md.contains("| `ransac.max_trials` | `ransac.threshold_px` | time ms |"),
        "{md}"
    );
    assert!(
        md.contains('★') && md.contains("Pareto front of error.corner_error_px"),
        "{md}"
    );
    for stem in ["pareto_error_corner_error_px", "pareto_inliers"] {
        let svg = std::fs::read_to_string(dir.join(format!("{stem}.svg"))).unwrap();
        assert!(
            svg.starts_with("<svg") && svg.contains("Pareto front"),
            "{stem}"
        );
        let png = std::fs::read(dir.join(format!("{stem}.png"))).unwrap();
        assert_eq!(&png[1..4], b"PNG");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_sweeps_are_clear_errors() {
    let dir = out_dir("bad");
    let d = dir.to_str().unwrap();
    let cases: [(&[&str], &str); 5] = [
        (&["--vary", "ransac.max_trials"], "missing `=`"),
        (
            &["--vary", "ransac.max_trails=1,2"],
            "did you mean `max_trials`",
        ),
        (
            &[
                "--vary",
                "ransac.max_trials=1,2",
                "--metric",
                "eror.corner_error_px",
            ],
            "no output `eror`",
        ),
        (
            &[
                "--vary",
                "ransac.max_trials=1,2",
                "--metric",
                "error.x:best",
            ],
            "unknown goal",
        ),
        (
            &["--vary", "ransac.max_trials=1,-2"],
            "`max_trials` must be ≥ 1, got -2",
        ),
    ];
    for (extra, expected) in cases {
        let mut args = vec!["sweep", "graphs/homography.ron", "--out", d];
        args.extend_from_slice(extra);
        if !extra.contains(&"--metric") {
            args.extend_from_slice(&["--metric", "error.corner_error_px"]);
        }
        let out = ocellus(&args);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{extra:?}: {stderr}");
        assert!(stderr.contains(expected), "{extra:?}: {stderr}");
    }
    // Nothing was written for a rejected sweep.
    assert!(!dir.exists());
}
