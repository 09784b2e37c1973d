//! Command-line interface: argument parsing and the subcommands. Exit codes: 0 success, 1 a node
//! failed or an output could not be written, 2 invalid graph or usage.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use clap::{Parser, Subcommand};
use ocellus_engine::{Diagnostics, Graph, Override, Registry, RunOptions, RunReport};

use crate::profile::Profile;
use crate::report::{print_diagnostics, render_bytes};

/// Exit code for an invalid graph or bad usage.
pub const EXIT_INVALID: u8 = 2;
/// Exit code for a run in which a node failed or an output could not be written.
pub const EXIT_FAILED: u8 = 1;

/// Ocellus: a dataflow engine for visual computing.
#[derive(Debug, Parser)]
#[command(name = "ocellus", version, about, max_term_width = 100)]
pub struct Cli {
    /// More log output (-v info, -vv debug); `OCELLUS_LOG` overrides.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    pub verbose: u8,
    /// Load operators from this plugin library (repeatable). `OCELLUS_PLUGIN_PATH` (files or
    /// folders, `:`-separated) and a graph's `plugins: [...]` are loaded too.
    #[arg(long = "plugin", value_name = "PATH", global = true)]
    pub plugin: Vec<PathBuf>,
    /// Load no plugin at all: neither `--plugin`, `OCELLUS_PLUGIN_PATH` nor a graph's `plugins`.
    #[arg(long = "no-plugins", global = true, conflicts_with = "plugin")]
    pub no_plugins: bool,
    /// Largest image a decoder accepts, in pixels (width × height), checked against the file's
    /// header before any pixel is decoded.
    #[arg(long, value_name = "PIXELS", global = true, help_heading = "Limits", default_value_t = ocellus_engine::limits::Limits::DEFAULT_MAX_IMAGE_PIXELS,
          value_parser = clap::value_parser!(u64).range(1..))]
    pub max_image_pixels: u64,
    /// Largest input file read and largest decoded image, in bytes (`4096`, `512M`, `4G`).
    #[arg(long, value_name = "BYTES", global = true, help_heading = "Limits", default_value = "4G",
          value_parser = ocellus_engine::limits::parse_bytes)]
    pub max_alloc_bytes: u64,
    /// Most elements a file may declare (vertices, faces, points, observations) and a node may
    /// output in one list.
    #[arg(long, value_name = "N", global = true, help_heading = "Limits", default_value_t = ocellus_engine::limits::Limits::DEFAULT_MAX_LIST_LEN,
          value_parser = clap::value_parser!(u64).range(1..))]
    pub max_list_len: u64,
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run a graph.
    Run(RunArgs),
    /// Check a graph and report every problem; exit 0 if valid, 2 if not.
    Check {
        /// Graph file.
        graph: PathBuf,
        /// Override a parameter, `NODE.PARAM=VALUE` (checked too).
        #[arg(long = "set", value_name = "NODE.PARAM=VALUE")]
        set: Vec<String>,
    },
    /// List operators, or show one in full.
    Ops {
        /// Show only this operator, in full.
        op: Option<String>,
        /// Machine-readable JSON.
        #[arg(long)]
        json: bool,
    },
    /// Run a graph over a grid of parameter values: time vs each metric, the Pareto front, a
    /// CSV, a Markdown table and plots.
    Sweep(crate::sweep::SweepArgs),
    /// Print a graph as Graphviz DOT.
    Dot {
        /// Graph file.
        graph: PathBuf,
    },
    /// Run a graph and print the snapshot summary of its outputs.
    Snapshot {
        /// Graph file.
        graph: PathBuf,
        /// Worker threads (0 = all cores).
        #[arg(long, default_value_t = 0)]
        threads: usize,
    },
}

/// `ocellus run`.
#[derive(Debug, clap::Args)]
pub struct RunArgs {
    /// Graph file.
    pub graph: PathBuf,
    /// Override a parameter: `NODE.PARAM=VALUE`, VALUE in RON (`1.5`, `[0, 0, 3]`, `"text"`; a
    /// bare word is a string).
    #[arg(long = "set", value_name = "NODE.PARAM=VALUE")]
    pub set: Vec<String>,
    /// Produce only these outputs (repeatable); default all.
    #[arg(long = "output", value_name = "NAME")]
    pub output: Vec<String>,
    /// Write the outputs into this folder.
    #[arg(long, value_name = "DIR")]
    pub emit: Option<PathBuf>,
    /// Worker threads for the scheduler and the operators (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Run the graph N times without the cache (for timing).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    pub repeat: u32,
    /// Write per-node timings as JSON.
    #[arg(long, value_name = "FILE.json")]
    pub profile: Option<PathBuf>,
    /// Of an animated graph, run only frame N (its number: the animation's `start` + i) as one
    /// ordinary run.
    #[arg(long, value_name = "N")]
    pub frame: Option<i64>,
    /// Of a streaming graph, run it as one batch run: every sequence as a whole list (the
    /// same values, all frames in memory).
    #[arg(long)]
    pub batch: bool,
    /// Persist node results here and reuse them across runs.
    #[arg(long, value_name = "DIR")]
    pub cache: Option<PathBuf>,
    /// Write a self-contained HTML report of the run (graph, per-node time and memory, cache
    /// reuse, output previews).
    #[arg(long, value_name = "FILE.html")]
    pub report: Option<PathBuf>,
    /// Run the graph's list maps (per-image, per-pair work) as tasks on the Ray cluster at this
    /// address (`127.0.0.1:6379`, `auto`). Needs Python with the `ocellus` package and Ray
    /// (`$OCELLUS_PYTHON`, else `python3`). Finished elements are kept in `--cache DIR`/items
    /// (default `~/.cache/ocellus/items`) and reused by the next run.
    #[arg(long, value_name = "ADDRESS", help_heading = "Distributed")]
    pub ray: Option<String>,
    /// With `--ray`: list elements per task (0 = about 64 tasks per list map, up to 16 each).
    #[arg(
        long,
        value_name = "N",
        default_value_t = 0,
        help_heading = "Distributed",
        requires = "ray"
    )]
    pub items_per_task: usize,
}

impl RunArgs {
    /// Run options for `threads` workers: the requested outputs, and the cache unless
    /// `--repeat` measures computation (results are never reused between repeats).
    pub fn options(&self, threads: usize) -> RunOptions {
        RunOptions {
            threads,
            outputs: self.output.clone(),
            cache_dir: if self.repeat > 1 {
                None
            } else {
                self.cache.clone()
            },
            ..RunOptions::default()
        }
    }
}

/// Runs a parsed command line.
pub fn dispatch(cli: Cli) -> ExitCode {
    ocellus_engine::limits::set(ocellus_engine::limits::Limits {
        max_image_pixels: cli.max_image_pixels,
        max_alloc_bytes: cli.max_alloc_bytes,
        max_list_len: cli.max_list_len,
    });
    let mut registry = match builtin_registry() {
        Ok(r) => r,
        Err(code) => return code,
    };
    let plugins = Plugins {
        enabled: !cli.no_plugins,
    };
    if let Err(code) = load_plugins(&mut registry, &cli.plugin, plugins) {
        return code;
    }
    let registry = &mut registry;
    match cli.command {
        Command::Run(args) => run(registry, &args, plugins),
        Command::Check { graph, set } => check(registry, &graph, &set, plugins),
        Command::Ops { op, json } => crate::ops::ops(registry, op.as_deref(), json),
        Command::Sweep(args) => crate::sweep::sweep(registry, &args, plugins),
        Command::Dot { graph } => match load(registry, &graph, &[], plugins) {
            Ok(g) => {
                print!("{}", g.to_dot());
                ExitCode::SUCCESS
            }
            Err(code) => code,
        },
        Command::Snapshot { graph, threads } => snapshot(registry, &graph, threads, plugins),
    }
}

/// Whether plugins may be loaded (`--no-plugins` turns them off).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Plugins {
    enabled: bool,
}

/// Environment variable naming plugin files or folders, `:`-separated.
const PLUGIN_PATH_ENV: &str = "OCELLUS_PLUGIN_PATH";

/// Loads `--plugin` files, then those of `OCELLUS_PLUGIN_PATH`; a failure is exit 2.
fn load_plugins(
    registry: &mut Registry,
    cli: &[PathBuf],
    plugins: Plugins,
) -> Result<(), ExitCode> {
    if !plugins.enabled {
        return Ok(());
    }
    let mut files = cli.to_vec();
    if let Some(list) = std::env::var_os(PLUGIN_PATH_ENV) {
        let list = list.to_string_lossy();
        match ocellus_engine::plugin::plugin_path_files(&list) {
            Ok(found) => files.extend(found),
            Err(message) => {
                eprintln!("error: {PLUGIN_PATH_ENV}: {message}");
                return Err(ExitCode::from(EXIT_INVALID));
            }
        }
    }
    for file in files {
        if let Err(e) = ocellus_engine::load_plugin(&file, registry) {
            eprintln!("error: {e}");
            return Err(ExitCode::from(EXIT_INVALID));
        }
    }
    Ok(())
}

fn builtin_registry() -> Result<Registry, ExitCode> {
    ocellus_nodes::builtin_registry().map_err(|e| {
        eprintln!("error: {e}");
        ExitCode::from(EXIT_FAILED)
    })
}

/// Parses overrides and loads a graph, printing diagnostics on failure.
pub(crate) fn load(
    registry: &mut Registry,
    path: &Path,
    set: &[String],
    plugins: Plugins,
) -> Result<Graph, ExitCode> {
    let mut diags = Diagnostics::default();
    let mut overrides = Vec::new();
    for arg in set {
        match Override::parse(arg) {
            Ok(o) => overrides.push(o),
            Err(d) => diags.push(*d),
        }
    }
    let result =
        ocellus_engine::load_graph_with_plugins(registry, path, &overrides, plugins.enabled);
    match result {
        Ok(graph) if diags.is_empty() => Ok(graph),
        Ok(_) => {
            print_diagnostics(&diags, path);
            Err(ExitCode::from(EXIT_INVALID))
        }
        Err(more) => {
            diags.0.extend(more.0);
            print_diagnostics(&diags, path);
            Err(ExitCode::from(EXIT_INVALID))
        }
    }
}

fn check(registry: &mut Registry, path: &Path, set: &[String], plugins: Plugins) -> ExitCode {
    match load(registry, path, set, plugins) {
        Ok(graph) => {
            let streams = match crate::streaming::stream_spec(registry, path, set) {
                Ok(Some(spec)) => format!(
                    ", streams (capacity {}, {} policy{})",
                    spec.capacity,
                    match spec.policy {
                        ocellus_engine::stream::Policy::Block => "block",
                        ocellus_engine::stream::Policy::Drop => "drop",
                    },
                    match spec.feedback.len() {
                        0 => String::new(),
                        1 => ", 1 feedback edge".to_string(),
                        n => format!(", {n} feedback edges"),
                    }
                ),
                Ok(None) => String::new(),
                Err(diags) => {
                    print_diagnostics(&diags, path);
                    return ExitCode::from(EXIT_INVALID);
                }
            };
            let frames = match crate::animation::timeline(registry, path, set) {
                Ok(Some(a)) => format!(", {} frames at {} fps", a.frames, a.fps),
                Ok(None) => String::new(),
                Err(diags) => {
                    print_diagnostics(&diags, path);
                    return ExitCode::from(EXIT_INVALID);
                }
            };
            println!(
                "{}: ok — graph `{}`, {} nodes, {} outputs{frames}{streams}",
                path.display(),
                graph.name,
                graph.nodes.len(),
                graph.outputs.len()
            );
            ExitCode::SUCCESS
        }
        Err(code) => code,
    }
}

fn snapshot(registry: &mut Registry, path: &Path, threads: usize, plugins: Plugins) -> ExitCode {
    let graph = match load(registry, path, &[], plugins) {
        Ok(g) => g,
        Err(code) => return code,
    };
    match crate::animation::timeline(registry, path, &[]) {
        Ok(Some(_)) => {
            // Each output as a list over the frames.
            return print_summary(ocellus_engine::testing::run_animated_graph(
                registry,
                path,
                threads,
                &[],
            ));
        }
        Ok(None) => {}
        Err(diags) => {
            print_diagnostics(&diags, path);
            return ExitCode::from(EXIT_INVALID);
        }
    }
    match crate::streaming::stream_spec(registry, path, &[]) {
        // Streamed, as the tests snapshot it: each per-frame output as its list over frames
        // (a batch run gives the same values, except that only a stream closes feedback loops).
        Ok(Some(_)) => {
            return print_summary(ocellus_engine::testing::run_stream_graph(
                registry,
                path,
                threads,
                &[],
            ));
        }
        Ok(None) => {}
        Err(diags) => {
            print_diagnostics(&diags, path);
            return ExitCode::from(EXIT_INVALID);
        }
    }
    let options = RunOptions {
        threads,
        ..RunOptions::default()
    };
    match ocellus_engine::run(&graph, &options) {
        Ok(report) => {
            print!(
                "{}",
                ocellus_engine::summary::summarize_outputs(&report.outputs)
            );
            report_failures(&report)
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(EXIT_INVALID)
        }
    }
}

/// Prints the snapshot summary of `outputs`, or the error.
fn print_summary(outputs: Result<Vec<(String, ocellus_engine::Value)>, String>) -> ExitCode {
    match outputs {
        Ok(outputs) => {
            print!("{}", ocellus_engine::summary::summarize_outputs(&outputs));
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(EXIT_FAILED)
        }
    }
}

fn report_failures(report: &RunReport) -> ExitCode {
    for w in &report.warnings {
        eprintln!("warning: {w}");
    }
    for f in &report.failures {
        eprintln!("error: {f}");
    }
    if report.failures.is_empty() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(EXIT_FAILED)
    }
}

fn run(registry: &mut Registry, args: &RunArgs, plugins: Plugins) -> ExitCode {
    let graph = match load(registry, &args.graph, &args.set, plugins) {
        Ok(g) => g,
        Err(code) => return code,
    };
    if let Err(code) = crate::run_report::refuse_unsupported(registry, args) {
        return code;
    }
    let threads = if args.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        args.threads
    };
    match crate::streaming::stream_spec(registry, &args.graph, &args.set) {
        Ok(Some(spec)) if !args.batch => {
            if let Some(frame) = args.frame {
                eprintln!(
                    "error: --frame {frame}: `{}` streams; --frame selects a frame of an animation",
                    args.graph.display()
                );
                return ExitCode::from(EXIT_INVALID);
            }
            if args.ray.is_some() {
                eprintln!(
                    "error: --ray distributes the list maps of a batch run; `{}` streams (add --batch)",
                    args.graph.display()
                );
                return ExitCode::from(EXIT_INVALID);
            }
            return crate::streaming::run_streamed(args, &graph, &spec, threads);
        }
        Ok(Some(spec)) if !spec.feedback.is_empty() => {
            let edge = &spec.feedback[0];
            eprintln!(
                "error: --batch: `{}` feeds `{}.{}` back into `{}.{}` frame by frame, which only a stream can do",
                args.graph.display(),
                edge.from.0,
                edge.from.1,
                edge.to.0,
                edge.to.1
            );
            return ExitCode::from(EXIT_INVALID);
        }
        Ok(_) => {}
        Err(diags) => {
            print_diagnostics(&diags, &args.graph);
            return ExitCode::from(EXIT_INVALID);
        }
    }
    let graph = match (
        crate::animation::timeline(registry, &args.graph, &args.set),
        args.frame,
    ) {
        (Ok(Some(_)), None) if args.ray.is_some() => {
            eprintln!(
                "error: --ray distributes the list maps of one run; `{}` is animated (add --frame N)",
                args.graph.display()
            );
            return ExitCode::from(EXIT_INVALID);
        }
        (Ok(Some(animated)), None) => {
            return crate::animation::run_animated(registry, args, &graph, &animated, threads);
        }
        (Ok(Some(animated)), Some(frame)) => {
            let first = animated.frame_number(0);
            let last = animated.frame_number(animated.frames - 1);
            let Some(index) = usize::try_from(frame - first)
                .ok()
                .filter(|_| (first..=last).contains(&frame))
            else {
                eprintln!("error: --frame {frame}: the animation has frames {first} to {last}");
                return ExitCode::from(EXIT_INVALID);
            };
            match animated.graph_at(registry, index) {
                Ok(g) => g,
                Err(diags) => {
                    print_diagnostics(&diags, &args.graph);
                    return ExitCode::from(EXIT_INVALID);
                }
            }
        }
        (Ok(None), Some(frame)) => {
            eprintln!(
                "error: --frame {frame}: `{}` has no `animation` section",
                args.graph.display()
            );
            return ExitCode::from(EXIT_INVALID);
        }
        (Ok(None), None) => graph,
        (Err(diags), _) => {
            print_diagnostics(&diags, &args.graph);
            return ExitCode::from(EXIT_INVALID);
        }
    };
    let driver = match &args.ray {
        Some(address) => match crate::ray::RayDriver::start(address) {
            Ok(d) => Some(Arc::new(d)),
            Err(e) => {
                eprintln!("error: {e}");
                return ExitCode::from(EXIT_FAILED);
            }
        },
        None => None,
    };
    let mut reports = Vec::with_capacity(args.repeat as usize);
    for _ in 0..args.repeat {
        let progress = Progress::start();
        let item_cache = if args.repeat > 1 {
            None
        } else {
            crate::ray::item_cache(args.cache.as_deref())
        };
        let options = RunOptions {
            progress: Some(progress.callback()),
            distribution: driver
                .as_ref()
                .map(|d| d.distribution(args.items_per_task, item_cache)),
            ..args.options(threads)
        };
        let result = ocellus_engine::run(&graph, &options);
        progress.finish();
        match result {
            Ok(report) => reports.push(report),
            Err(e) => {
                eprintln!("error: {e}");
                return ExitCode::from(EXIT_INVALID);
            }
        }
    }
    if let Some(driver) = &driver {
        driver.close();
    }
    let Some(last) = reports.last() else {
        return ExitCode::from(EXIT_INVALID);
    };
    let profile = Profile::from_reports(&reports);
    let mut code = report_failures(last);

    let mut emitted = None;
    if let Some(dir) = &args.emit {
        match emit_all(dir, last) {
            Ok(()) => emitted = Some(dir),
            Err(message) => {
                eprintln!("error: {message}");
                code = ExitCode::from(EXIT_FAILED);
            }
        }
    } else {
        print!(
            "{}",
            ocellus_engine::summary::summarize_outputs(&last.outputs)
        );
    }
    if let Some(path) = &args.profile
        && let Err(e) = profile.write(path)
    {
        eprintln!("error: cannot write profile {}: {e}", path.display());
        code = ExitCode::from(EXIT_FAILED);
    }
    let rss = crate::report::peak_rss_bytes()
        .map(|b| format!(", process peak {}", render_bytes(b)))
        .unwrap_or_default();
    let timing = if args.repeat > 1 {
        format!(
            "median {:.2} ms over {} runs",
            profile.total_median_ms, args.repeat
        )
    } else {
        format!("{:.2} ms", last.elapsed.as_secs_f64() * 1e3)
    };
    eprintln!(
        "ran `{}` in {timing} on {threads} thread{}: {} nodes — {}; peak outputs {}{rss}",
        graph.name,
        if threads == 1 { "" } else { "s" },
        graph.nodes.len(),
        last.summary_line(),
        render_bytes(last.peak_bytes as u64),
    );
    if let Some(dir) = emitted {
        eprintln!(
            "outputs: {} ({} written)",
            dir.display(),
            last.outputs.len()
        );
    }
    if let Some(path) = &args.report
        && let Err(message) = crate::run_report::write_report(path, args, &graph, &reports, threads)
    {
        eprintln!("error: {message}");
        code = ExitCode::from(EXIT_FAILED);
    }
    code
}

fn emit_all(dir: &Path, report: &RunReport) -> Result<(), String> {
    ocellus_engine::temp_files::prepare_dir(dir)
        .map_err(|e| format!("cannot create {}: {e}", dir.display()))?;
    let mut failed = Vec::new();
    for (name, value) in &report.outputs {
        if let Err(e) = ocellus_engine::emit::emit_value(dir, name, value) {
            failed.push(format!("output `{name}`: {e}"));
        }
    }
    if failed.is_empty() {
        Ok(())
    } else {
        Err(failed.join("\n"))
    }
}

/// A progress bar on a terminal, shown once a run has taken longer than a second.
struct Progress {
    done: Arc<AtomicUsize>,
    total: Arc<AtomicUsize>,
    finished: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Progress {
    fn start() -> Progress {
        let done = Arc::new(AtomicUsize::new(0));
        let total = Arc::new(AtomicUsize::new(0));
        let finished = Arc::new(AtomicBool::new(false));
        let thread = std::io::stderr().is_terminal().then(|| {
            let (done, total, finished) =
                (Arc::clone(&done), Arc::clone(&total), Arc::clone(&finished));
            std::thread::spawn(move || {
                let start = Instant::now();
                while start.elapsed() < Duration::from_secs(1) {
                    if finished.load(Ordering::Relaxed) {
                        return;
                    }
                    std::thread::sleep(Duration::from_millis(20));
                }
                let bar = indicatif::ProgressBar::new(total.load(Ordering::Relaxed) as u64);
                if let Ok(style) = indicatif::ProgressStyle::with_template(
                    "{elapsed_precise} [{bar:40}] {pos}/{len} nodes",
                ) {
                    bar.set_style(style.progress_chars("=> "));
                }
                while !finished.load(Ordering::Relaxed) {
                    bar.set_length(total.load(Ordering::Relaxed) as u64);
                    bar.set_position(done.load(Ordering::Relaxed) as u64);
                    std::thread::sleep(Duration::from_millis(50));
                }
                bar.finish_and_clear();
            })
        });
        Progress {
            done,
            total,
            finished,
            thread,
        }
    }

    fn callback(&self) -> ocellus_engine::exec::ProgressFn {
        let (done, total) = (Arc::clone(&self.done), Arc::clone(&self.total));
        Arc::new(move |d, t| {
            done.store(d, Ordering::Relaxed);
            total.store(t, Ordering::Relaxed);
        })
    }

    fn finish(mut self) {
        self.finished.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
