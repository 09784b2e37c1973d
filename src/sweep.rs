//! `ocellus sweep`: runs a graph over a grid of parameter values and measures the speed–accuracy
//! trade — time of the nodes the parameters reach vs each metric — with its Pareto front, as a
//! CSV, a Markdown table and plots.
//!
//! Every grid point runs with one in-memory cache shared by the whole sweep and with the varied
//! nodes marked for recomputation (`RunOptions::recompute`): what the parameters do not reach
//! (feature detection, say, when RANSAC's threshold varies) is computed once and reused, while
//! the varied nodes and everything downstream of them run afresh in every repeat and are timed.
//! One untimed warm-up run fills the cache first, so the first grid point is timed like the rest.

use std::collections::BTreeSet;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;

use ocellus_engine::cache::MemoryCache;
use ocellus_engine::exec::NodeStatus;
use ocellus_engine::{Registry, RunOptions, Value};

use crate::cli::{EXIT_FAILED, EXIT_INVALID, Plugins, load};
use crate::plot::{ParetoChart, format_number, pareto_png, pareto_svg};

/// `ocellus sweep`.
#[derive(Debug, clap::Args)]
pub struct SweepArgs {
    /// Graph file.
    pub graph: PathBuf,
    /// A parameter and its values, `NODE.PARAM=V1,V2,...` (repeatable: the grid is the product,
    /// the first `--vary` changing slowest). Values are RON; commas inside brackets, parentheses
    /// or quotes do not split (`--vary warp.matrix=[[1,0,0],[0,1,0]],[[2,0,0],[0,2,0]]`).
    #[arg(long = "vary", value_name = "NODE.PARAM=V1,V2,...", required = true)]
    pub vary: Vec<String>,
    /// What to measure: a graph output, `OUTPUT` (a number) or `OUTPUT.FIELD` (a field of a
    /// Metrics output), minimized unless suffixed `:max` (`quality.psnr_db:max`); `:min` is
    /// accepted too. Repeatable.
    #[arg(long = "metric", value_name = "OUTPUT[.FIELD][:max]", required = true)]
    pub metric: Vec<String>,
    /// Timed runs per grid point; the time is their median.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..))]
    pub repeat: u32,
    /// Folder for sweep.csv, sweep.md and the plots (pareto_METRIC.svg / .png).
    #[arg(long, value_name = "DIR", default_value = "sweep")]
    pub out: PathBuf,
    /// Fixed overrides applied to every grid point, `NODE.PARAM=VALUE`.
    #[arg(long = "set", value_name = "NODE.PARAM=VALUE")]
    pub set: Vec<String>,
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
}

/// One `--vary`: `node.param` and its values (RON text).
#[derive(Debug, Clone, PartialEq)]
pub struct Vary {
    /// `NODE.PARAM`.
    pub target: String,
    /// The node part.
    pub node: String,
    /// The values, as written.
    pub values: Vec<String>,
}

/// Parses `NODE.PARAM=V1,V2,...`.
pub fn parse_vary(arg: &str) -> Result<Vary, String> {
    let Some((target, values)) = arg.split_once('=') else {
        return Err(format!(
            "--vary {arg}: missing `=`; write `--vary NODE.PARAM=V1,V2,...`"
        ));
    };
    let target = target.trim();
    let Some((node, param)) = target.rsplit_once('.') else {
        return Err(format!(
            "--vary {arg}: `{target}` is not NODE.PARAM; write `--vary NODE.PARAM=V1,V2,...`"
        ));
    };
    if node.is_empty() || param.is_empty() {
        return Err(format!("--vary {arg}: `{target}` is not NODE.PARAM"));
    }
    let values = split_top_level(values)?;
    if values.is_empty() || values.iter().any(String::is_empty) {
        return Err(format!("--vary {arg}: an empty value"));
    }
    let mut seen = BTreeSet::new();
    for v in &values {
        if !seen.insert(v.as_str()) {
            return Err(format!("--vary {arg}: the value `{v}` is given twice"));
        }
    }
    Ok(Vary {
        target: target.to_string(),
        node: node.to_string(),
        values,
    })
}

/// Splits at commas outside brackets, parentheses, braces and double quotes; trims each part.
fn split_top_level(text: &str) -> Result<Vec<String>, String> {
    let mut parts = Vec::new();
    let mut depth = 0i32;
    let mut quoted = false;
    let mut escaped = false;
    let mut current = String::new();
    for c in text.chars() {
        if quoted {
            current.push(c);
            match (escaped, c) {
                (true, _) => escaped = false,
                (false, '\\') => escaped = true,
                (false, '"') => quoted = false,
                _ => {}
            }
            continue;
        }
        match c {
            '"' => quoted = true,
            '[' | '(' | '{' => depth += 1,
            ']' | ')' | '}' => depth -= 1,
            ',' if depth == 0 => {
                parts.push(current.trim().to_string());
                current.clear();
                continue;
            }
            _ => {}
        }
        if depth < 0 {
            return Err(format!("unbalanced brackets in `{text}`"));
        }
        current.push(c);
    }
    if quoted || depth != 0 {
        return Err(format!("unbalanced brackets or quotes in `{text}`"));
    }
    parts.push(current.trim().to_string());
    Ok(parts)
}

/// Whether a metric is better large or small.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Goal {
    /// Smaller is better (errors, residuals).
    Min,
    /// Larger is better (PSNR, accuracy, recall).
    Max,
}

/// One `--metric`.
#[derive(Debug, Clone, PartialEq)]
pub struct Metric {
    /// As written, without the goal suffix: `OUTPUT` or `OUTPUT.FIELD`.
    pub name: String,
    /// The graph output.
    pub output: String,
    /// The field of a Metrics output.
    pub field: Option<String>,
    /// Minimize or maximize.
    pub goal: Goal,
}

/// Parses `OUTPUT[.FIELD][:min|:max]`.
pub fn parse_metric(arg: &str) -> Result<Metric, String> {
    let (name, goal) = match arg.rsplit_once(':') {
        Some((name, "max")) => (name, Goal::Max),
        Some((name, "min")) => (name, Goal::Min),
        Some((_, other)) => {
            return Err(format!(
                "--metric {arg}: unknown goal `:{other}`; write `:min` or `:max`"
            ));
        }
        None => (arg, Goal::Min),
    };
    let name = name.trim();
    if name.is_empty() {
        return Err(format!("--metric {arg}: empty"));
    }
    let (output, field) = match name.split_once('.') {
        Some((o, f)) if !o.is_empty() && !f.is_empty() => (o.to_string(), Some(f.to_string())),
        Some(_) => return Err(format!("--metric {arg}: write OUTPUT or OUTPUT.FIELD")),
        None => (name.to_string(), None),
    };
    Ok(Metric {
        name: name.to_string(),
        output,
        field,
        goal,
    })
}

/// The number a metric reads from a run's outputs.
fn read_metric(metric: &Metric, outputs: &[(String, Value)]) -> Result<f64, String> {
    let Some((_, value)) = outputs.iter().find(|(n, _)| *n == metric.output) else {
        return Err(format!("output `{}` was not produced", metric.output));
    };
    let number = |v: &Value| -> Option<f64> {
        match v {
            Value::Scalar(x) => Some(*x),
            Value::Integer(i) => Some(*i as f64),
            Value::Bool(b) => Some(f64::from(u8::from(*b))),
            Value::Matrix(m) if m.data.len() == 1 => Some(m.data[0]),
            _ => None,
        }
    };
    match (&metric.field, value) {
        (Some(field), Value::Metrics(m)) => m.get(field).copied().ok_or_else(|| {
            let fields: Vec<&str> = m.keys().map(String::as_str).collect();
            format!(
                "output `{}` has no field `{field}` (it has: {})",
                metric.output,
                fields.join(", ")
            )
        }),
        (Some(field), other) => Err(format!(
            "output `{}` is {}, not Metrics: it has no field `{field}`",
            metric.output,
            other.port_type()
        )),
        (None, Value::Metrics(m)) => {
            let fields: Vec<&str> = m.keys().map(String::as_str).collect();
            Err(format!(
                "output `{}` is Metrics: name a field, `{}.FIELD` (one of: {})",
                metric.output,
                metric.output,
                fields.join(", ")
            ))
        }
        (None, other) => number(other).ok_or_else(|| {
            format!(
                "output `{}` is {}, not a number",
                metric.output,
                other.port_type()
            )
        }),
    }
}

/// The result of one grid point.
#[derive(Debug, Clone, PartialEq)]
pub struct Point {
    /// One value per `--vary`, as written.
    pub values: Vec<String>,
    /// Median over the repeats of the summed time of the recomputed nodes, ms.
    pub time_ms: f64,
    /// Median wall time of the whole run, ms (includes reading the cache).
    pub wall_ms: f64,
    /// One value per metric (NaN where it could not be read).
    pub metrics: Vec<f64>,
    /// Empty, or why the point has no (complete) result.
    pub problem: String,
}

/// Indices of the Pareto front of (time, value) with `goal`: the points no other point beats
/// in both (at most as slow and at least as good, better in one). Non-finite points never
/// belong; equal points all do. Sorted by time.
pub fn pareto_front(points: &[(f64, f64)], goal: Goal) -> Vec<usize> {
    let better = |a: f64, b: f64| match goal {
        Goal::Min => a < b,
        Goal::Max => a > b,
    };
    let not_worse = |a: f64, b: f64| a == b || better(a, b);
    let finite = |(t, v): (f64, f64)| t.is_finite() && v.is_finite();
    let mut front: Vec<usize> = (0..points.len())
        .filter(|&i| finite(points[i]))
        .filter(|&i| {
            let (t, v) = points[i];
            !points.iter().enumerate().any(|(j, &(tj, vj))| {
                j != i
                    && finite((tj, vj))
                    && tj <= t
                    && not_worse(vj, v)
                    && (tj < t || better(vj, v))
            })
        })
        .collect();
    front.sort_by(|&a, &b| points[a].0.total_cmp(&points[b].0).then(a.cmp(&b)));
    front
}

/// Median of unsorted samples (NaN when there are none).
fn median(mut samples: Vec<f64>) -> f64 {
    if samples.is_empty() {
        return f64::NAN;
    }
    samples.sort_by(f64::total_cmp);
    crate::profile::median(&samples)
}

/// Runs `ocellus sweep`.
pub fn sweep(registry: &mut Registry, args: &SweepArgs, plugins: Plugins) -> ExitCode {
    let mut varies = Vec::new();
    for arg in &args.vary {
        match parse_vary(arg) {
            Ok(v) => varies.push(v),
            Err(e) => {
                eprintln!("error: {e}");
                return ExitCode::from(EXIT_INVALID);
            }
        }
    }
    let mut targets = BTreeSet::new();
    for v in &varies {
        if !targets.insert(v.target.as_str()) {
            eprintln!("error: --vary {}: given twice", v.target);
            return ExitCode::from(EXIT_INVALID);
        }
    }
    let mut metrics = Vec::new();
    for arg in &args.metric {
        match parse_metric(arg) {
            Ok(m) => metrics.push(m),
            Err(e) => {
                eprintln!("error: {e}");
                return ExitCode::from(EXIT_INVALID);
            }
        }
    }
    match (
        crate::streaming::stream_spec(registry, &args.graph, &args.set),
        crate::animation::timeline(registry, &args.graph, &args.set),
    ) {
        (Ok(None), Ok(None)) => {}
        (Ok(Some(_)), _) | (_, Ok(Some(_))) => {
            eprintln!(
                "error: `{}` streams or is animated; sweep runs ordinary graphs (sweep a `--frame` or a batch run by hand)",
                args.graph.display()
            );
            return ExitCode::from(EXIT_INVALID);
        }
        (Err(diags), _) | (_, Err(diags)) => {
            crate::report::print_diagnostics(&diags, &args.graph);
            return ExitCode::from(EXIT_INVALID);
        }
    }

    // The grid, first --vary slowest; every point's graph is loaded (and so checked) first.
    let count: usize = varies.iter().map(|v| v.values.len()).product();
    let mut grid = Vec::with_capacity(count);
    for k in 0..count {
        let mut rest = k;
        let mut values = vec![String::new(); varies.len()];
        for (slot, v) in values.iter_mut().zip(&varies).rev() {
            *slot = v.values[rest % v.values.len()].clone();
            rest /= v.values.len();
        }
        let mut set = args.set.clone();
        set.extend(
            varies
                .iter()
                .zip(&values)
                .map(|(v, value)| format!("{}={value}", v.target)),
        );
        match load(registry, &args.graph, &set, plugins) {
            Ok(graph) => grid.push((values, graph)),
            Err(code) => return code,
        }
    }
    let Some((_, first)) = grid.first() else {
        return ExitCode::from(EXIT_INVALID);
    };
    let mut outputs: Vec<String> = Vec::new();
    for m in &metrics {
        if !first.outputs.iter().any(|o| o.name == m.output) {
            let names: Vec<&str> = first.outputs.iter().map(|o| o.name.as_str()).collect();
            eprintln!(
                "error: --metric {}: the graph has no output `{}` (it has: {})",
                m.name,
                m.output,
                names.join(", ")
            );
            return ExitCode::from(EXIT_INVALID);
        }
        if !outputs.contains(&m.output) {
            outputs.push(m.output.clone());
        }
    }
    let recompute: Vec<String> = varies
        .iter()
        .map(|v| v.node.clone())
        .collect::<BTreeSet<_>>()
        .into_iter()
        .collect();
    let cache = Arc::new(MemoryCache::new());
    let options = RunOptions {
        threads: args.threads,
        outputs,
        memory_cache: Some(Arc::clone(&cache)),
        recompute,
        ..RunOptions::default()
    };

    // Warm-up: fills the cache with what no parameter reaches.
    if let Err(e) = ocellus_engine::run(first, &options) {
        eprintln!("error: {e}");
        return ExitCode::from(EXIT_INVALID);
    }
    let mut points = Vec::with_capacity(grid.len());
    for (k, (values, graph)) in grid.iter().enumerate() {
        let mut times = Vec::new();
        let mut walls = Vec::new();
        let mut last = None;
        for _ in 0..args.repeat {
            let report = match ocellus_engine::run(graph, &options) {
                Ok(r) => r,
                Err(e) => {
                    eprintln!("error: {e}");
                    return ExitCode::from(EXIT_INVALID);
                }
            };
            times.push(
                report
                    .nodes
                    .iter()
                    .filter(|n| matches!(n.status, NodeStatus::Computed | NodeStatus::Failed))
                    .fold(0.0, |sum, n| sum + n.elapsed.as_secs_f64() * 1e3),
            );
            walls.push(report.elapsed.as_secs_f64() * 1e3);
            last = Some(report);
        }
        // Keep the cache to what the next point can use: the unchanged upstream.
        cache.end_generation();
        let Some(report) = last else {
            return ExitCode::from(EXIT_INVALID);
        };
        let mut problems: Vec<String> = report.failures.iter().map(|f| f.to_string()).collect();
        let values_read: Vec<f64> = metrics
            .iter()
            .map(|m| match read_metric(m, &report.outputs) {
                Ok(v) => v,
                Err(e) => {
                    if report.failures.is_empty() {
                        problems.push(e);
                    }
                    f64::NAN
                }
            })
            .collect();
        let point = Point {
            values: values.clone(),
            time_ms: median(times),
            wall_ms: median(walls),
            metrics: values_read,
            problem: problems.join("; "),
        };
        eprintln!(
            "[{}/{}] {} — {} ms{}",
            k + 1,
            grid.len(),
            label_of(&varies, &point.values),
            format_number(point.time_ms),
            metrics
                .iter()
                .zip(&point.metrics)
                .map(|(m, v)| format!(", {} {}", m.name, format_number(*v)))
                .collect::<String>()
        );
        points.push(point);
    }

    let fronts: Vec<Vec<usize>> = metrics
        .iter()
        .enumerate()
        .map(|(j, m)| {
            let xy: Vec<(f64, f64)> = points.iter().map(|p| (p.time_ms, p.metrics[j])).collect();
            pareto_front(&xy, m.goal)
        })
        .collect();
    let csv = to_csv(&varies, &metrics, &points, &fronts);
    let markdown = to_markdown(
        &args.graph,
        &varies,
        &metrics,
        &points,
        &fronts,
        args.repeat,
    );
    let mut code = ExitCode::SUCCESS;
    let write = |path: &Path, bytes: &[u8]| -> bool {
        match ocellus_engine::image_io::write_atomic(path, bytes) {
            Ok(()) => true,
            Err(e) => {
                eprintln!("error: cannot write {}: {e}", path.display());
                false
            }
        }
    };
    if let Err(e) = ocellus_engine::temp_files::prepare_dir(&args.out) {
        eprintln!("error: cannot create {}: {e}", args.out.display());
        return ExitCode::from(EXIT_FAILED);
    }
    let mut written = Vec::new();
    for (name, bytes) in [
        ("sweep.csv", csv.into_bytes()),
        ("sweep.md", markdown.clone().into_bytes()),
    ] {
        let path = args.out.join(name);
        if write(&path, &bytes) {
            written.push(path);
        } else {
            code = ExitCode::from(EXIT_FAILED);
        }
    }
    for (j, m) in metrics.iter().enumerate() {
        let chart = ParetoChart {
            title: format!(
                "{} vs time ({}): Pareto front",
                m.name,
                match m.goal {
                    Goal::Min => "lower is better",
                    Goal::Max => "higher is better",
                }
            ),
            x_label: format!(
                "time of the recomputed nodes, ms (median of {})",
                args.repeat
            ),
            y_label: m.name.clone(),
            points: points.iter().map(|p| (p.time_ms, p.metrics[j])).collect(),
            front: fronts[j].clone(),
            labels: points
                .iter()
                .map(|p| label_of(&varies, &p.values))
                .collect(),
        };
        let stem = format!("pareto_{}", file_stem(&m.name));
        let rendered = [
            ("svg", pareto_svg(&chart).map(String::into_bytes)),
            ("png", pareto_png(&chart)),
        ];
        for (ext, bytes) in rendered {
            let path = args.out.join(format!("{stem}.{ext}"));
            match bytes {
                Ok(bytes) if write(&path, &bytes) => written.push(path),
                Ok(_) => code = ExitCode::from(EXIT_FAILED),
                Err(e) => {
                    eprintln!("error: cannot draw {}: {e}", path.display());
                    code = ExitCode::from(EXIT_FAILED);
                }
            }
        }
    }
    print!("{markdown}");
    for path in &written {
        eprintln!("wrote {}", path.display());
    }
    if points.iter().any(|p| !p.problem.is_empty()) {
        eprintln!("warning: some grid points have no result; see the `problem` column");
    }
    code
}

/// `a=1 b=3` for a point.
fn label_of(varies: &[Vary], values: &[String]) -> String {
    varies
        .iter()
        .zip(values)
        .map(|(v, value)| {
            let param = v
                .target
                .rsplit_once('.')
                .map_or(v.target.as_str(), |(_, p)| p);
            format!("{param}={value}")
        })
        .collect::<Vec<_>>()
        .join(" ")
}

/// A file-name-safe version of a metric name.
fn file_stem(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '_' || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// A CSV field, quoted when needed.
fn csv_field(text: &str) -> String {
    if text.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", text.replace('"', "\"\""))
    } else {
        text.to_string()
    }
}

/// `sweep.csv`: one row per grid point — the varied values, times, metrics, front membership
/// per metric (1/0), and the problem, if any.
pub fn to_csv(
    varies: &[Vary],
    metrics: &[Metric],
    points: &[Point],
    fronts: &[Vec<usize>],
) -> String {
    let mut header: Vec<String> = varies.iter().map(|v| csv_field(&v.target)).collect();
    header.push("time_ms".into());
    header.push("wall_ms".into());
    header.extend(metrics.iter().map(|m| csv_field(&m.name)));
    header.extend(
        metrics
            .iter()
            .map(|m| csv_field(&format!("pareto:{}", m.name))),
    );
    header.push("problem".into());
    let mut out = header.join(",") + "\n";
    for (i, p) in points.iter().enumerate() {
        let mut row: Vec<String> = p.values.iter().map(|v| csv_field(v)).collect();
        row.push(format!("{}", p.time_ms));
        row.push(format!("{}", p.wall_ms));
        row.extend(p.metrics.iter().map(|v| {
            if v.is_finite() {
                format!("{v}")
            } else {
                String::new()
            }
        }));
        row.extend(
            fronts
                .iter()
                .map(|f| if f.contains(&i) { "1" } else { "0" }.to_string()),
        );
        row.push(csv_field(&p.problem));
        out += &(row.join(",") + "\n");
    }
    out
}

/// `sweep.md`: the table (front members starred per metric) and the front of each metric.
pub fn to_markdown(
    graph: &Path,
    varies: &[Vary],
    metrics: &[Metric],
    points: &[Point],
    fronts: &[Vec<usize>],
    repeat: u32,
) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "Sweep of `{}`: {} settings, time = median of {repeat} runs of the nodes the varied parameters reach (★ = on the Pareto front of time and that metric).\n",
        graph.display(),
        points.len()
    );
    let mut header: Vec<String> = varies.iter().map(|v| format!("`{}`", v.target)).collect();
    header.push("time ms".into());
    header.extend(metrics.iter().map(|m| {
        format!(
            "{} ({})",
            m.name,
            match m.goal {
                Goal::Min => "min",
                Goal::Max => "max",
            }
        )
    }));
    let _ = writeln!(out, "| {} |", header.join(" | "));
    let _ = writeln!(
        out,
        "|{}",
        header
            .iter()
            .enumerate()
            .map(|(k, _)| if k < varies.len() { "---|" } else { "---:|" })
            .collect::<String>()
    );
    for (i, p) in points.iter().enumerate() {
        let mut row: Vec<String> = p.values.clone();
        row.push(format_number(p.time_ms));
        for (j, v) in p.metrics.iter().enumerate() {
            let star = if fronts[j].contains(&i) { " ★" } else { "" };
            row.push(if v.is_finite() {
                format!("{}{star}", format_number(*v))
            } else {
                "–".into()
            });
        }
        let _ = writeln!(out, "| {} |", row.join(" | "));
    }
    for (j, m) in metrics.iter().enumerate() {
        let steps: Vec<String> = fronts[j]
            .iter()
            .map(|&i| {
                format!(
                    "{} ({} ms, {})",
                    label_of(varies, &points[i].values),
                    format_number(points[i].time_ms),
                    format_number(points[i].metrics[j])
                )
            })
            .collect();
        let _ = writeln!(out, "\nPareto front of {}: {}.", m.name, steps.join(" → "));
    }
    let problems: Vec<String> = points
        .iter()
        .filter(|p| !p.problem.is_empty())
        .map(|p| format!("- {}: {}", label_of(varies, &p.values), p.problem))
        .collect();
    if !problems.is_empty() {
        let _ = writeln!(out, "\nSettings without a result:\n{}", problems.join("\n"));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vary_values_split_at_top_level_commas() {
        let v = parse_vary("ransac.threshold_px=1, 2.5,8").unwrap();
        assert_eq!(v.node, "ransac");
        assert_eq!(v.values, ["1", "2.5", "8"]);
        let v = parse_vary("warp.matrix=[[1,0],[0,1]],[[2,0],[0,2]]").unwrap();
        assert_eq!(v.values, ["[[1,0],[0,1]]", "[[2,0],[0,2]]"]);
        let v = parse_vary(r#"io.path="a,b.png","c.png""#).unwrap();
        assert_eq!(v.values, [r#""a,b.png""#, r#""c.png""#]);
        let v = parse_vary("sub/inner.k=Some((1, 2)),None").unwrap();
        assert_eq!((v.node.as_str(), v.values.len()), ("sub/inner", 2));
        for bad in [
            "ransac.threshold_px",
            "threshold=1",
            "a.b=1,,2",
            "a.b=[1,2",
            "a.b=1,1",
            ".b=1",
        ] {
            assert!(parse_vary(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn metrics_parse_with_goals() {
        let m = parse_metric("error.corner_error_px").unwrap();
        assert_eq!(
            (m.output.as_str(), m.field.as_deref(), m.goal),
            ("error", Some("corner_error_px"), Goal::Min)
        );
        let m = parse_metric("quality.psnr_db:max").unwrap();
        assert_eq!((m.name.as_str(), m.goal), ("quality.psnr_db", Goal::Max));
        let m = parse_metric("inliers").unwrap();
        assert_eq!((m.output.as_str(), m.field), ("inliers", None));
        for bad in ["", "x.", ".y", "a.b:best"] {
            assert!(parse_metric(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn metric_values_are_read_from_outputs() {
        let mut fields = ocellus_engine::value::Metrics::new();
        fields.insert("rms".into(), 0.5);
        let outputs = vec![
            ("m".to_string(), Value::metrics(fields)),
            ("n".to_string(), Value::Integer(7)),
        ];
        let get = |arg: &str| read_metric(&parse_metric(arg).unwrap(), &outputs);
        assert_eq!(get("m.rms"), Ok(0.5));
        assert_eq!(get("n"), Ok(7.0));
        assert!(get("m").unwrap_err().contains("m.FIELD"));
        assert!(get("m.x").unwrap_err().contains("has: rms"));
        assert!(get("n.x").unwrap_err().contains("not Metrics"));
        assert!(get("z").unwrap_err().contains("not produced"));
    }

    /// The front by brute force on hand-made points: dominated points and NaNs are left out,
    /// ties in both stay, and the goal flips what "better" means.
    #[test]
    fn pareto_fronts() {
        let pts = [
            (1.0, 9.0),
            (2.0, 4.0),
            (3.0, 5.0),
            (4.0, 1.0),
            (2.0, 4.0),
            (0.5, f64::NAN),
            (5.0, 1.0),
        ];
        assert_eq!(pareto_front(&pts, Goal::Min), vec![0, 1, 4, 3]);
        // Maximizing: the fastest point is best in time, and nothing beats 9.0.
        assert_eq!(pareto_front(&pts, Goal::Max), vec![0]);
        let up = [(1.0, 1.0), (2.0, 3.0), (3.0, 2.0), (4.0, 5.0)];
        assert_eq!(pareto_front(&up, Goal::Max), vec![0, 1, 3]);
        assert!(pareto_front(&[], Goal::Min).is_empty());
    }

    /// Every point off the front is dominated by a point on it, and no front point by any.
    #[test]
    fn pareto_front_properties_on_a_grid() {
        let pts: Vec<(f64, f64)> = (0..40)
            .map(|i| (((i * 7) % 13) as f64, ((i * 11) % 17) as f64))
            .collect();
        let front = pareto_front(&pts, Goal::Min);
        let dominates =
            |a: (f64, f64), b: (f64, f64)| a.0 <= b.0 && a.1 <= b.1 && (a.0 < b.0 || a.1 < b.1);
        for (i, &p) in pts.iter().enumerate() {
            let on = front.contains(&i);
            assert_eq!(on, !pts.iter().any(|&q| dominates(q, p)), "point {i} {p:?}");
            if !on {
                assert!(front.iter().any(|&f| dominates(pts[f], p)));
            }
        }
    }

    #[test]
    fn tables_mark_the_front() {
        let varies = vec![parse_vary("r.k=1,2").unwrap()];
        let metrics = vec![parse_metric("e.x").unwrap()];
        let points = vec![
            Point {
                values: vec!["1".into()],
                time_ms: 1.0,
                wall_ms: 2.0,
                metrics: vec![3.0],
                problem: String::new(),
            },
            Point {
                values: vec!["2".into()],
                time_ms: 2.0,
                wall_ms: 3.0,
                metrics: vec![f64::NAN],
                problem: "node `r` failed, \"x\"".into(),
            },
        ];
        let fronts = vec![vec![0]];
        let csv = to_csv(&varies, &metrics, &points, &fronts);
        assert_eq!(
            csv,
            "r.k,time_ms,wall_ms,e.x,pareto:e.x,problem\n1,1,2,3,1,\n2,2,3,,0,\"node `r` failed, \"\"x\"\"\"\n"
        );
        let md = to_markdown(Path::new("g.ron"), &varies, &metrics, &points, &fronts, 3);
        assert!(md.contains("| 1 | 1 | 3 ★ |"), "{md}");
        assert!(md.contains("| 2 | 2 | – |"), "{md}");
        assert!(md.contains("Pareto front of e.x: k=1 (1 ms, 3)."), "{md}");
        assert!(md.contains("Settings without a result"), "{md}");
    }
}
