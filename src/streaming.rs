//! `ocellus run` on a graph with a `stream` section: the frames flow through the pipelined
//! stages (see `ocellus_engine::stream`); `--emit` writes each frame as it arrives.

use std::path::Path;
use std::process::ExitCode;

use ocellus_engine::sequence_write::FrameEmitter;
use ocellus_engine::stream::{StreamReport, StreamSpec, run_stream};
use ocellus_engine::{Graph, Registry, Value};

use crate::cli::{EXIT_FAILED, EXIT_INVALID, RunArgs};
use crate::report::render_bytes;

/// The resident set size is sampled at every frame and reported per window of this many
/// frames (its largest sample in the window), plus once at the end. The largest sample, not
/// the current one: how many packets sit in the channels when a frame reaches the sink
/// varies from frame to frame, and with it the resident size by tens of megabytes; the
/// window maximum is the bound that matters, and it is steady when memory is.
const RSS_EVERY: usize = 100;

/// The stream section of a graph file, if it has one.
pub fn stream_spec(
    registry: &Registry,
    path: &Path,
    set: &[String],
) -> Result<Option<StreamSpec>, ocellus_engine::Diagnostics> {
    let overrides = crate::animation::parse_overrides(set)?;
    ocellus_engine::stream::load_streamed_file(registry, path, &overrides).map(|(_, s)| s)
}

/// The process's current resident set size (Linux `/proc/self/statm`).
pub fn current_rss_bytes() -> Option<u64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    Some(pages * 4096)
}

/// Streams `graph` (`--repeat` times), emitting the last repeat's frames.
pub fn run_streamed(args: &RunArgs, graph: &Graph, spec: &StreamSpec, threads: usize) -> ExitCode {
    let mut reports: Vec<StreamReport> = Vec::new();
    let mut rss: Vec<(usize, u64)> = Vec::new();
    let mut last_frame: Option<(usize, Vec<(String, Value)>)> = None;
    let mut code = ExitCode::SUCCESS;
    for repeat in 0..args.repeat {
        let last_repeat = repeat + 1 == args.repeat;
        let options = args.options(threads);
        if let (Some(dir), true) = (&args.emit, last_repeat)
            && let Err(e) = std::fs::create_dir_all(dir)
        {
            eprintln!("error: cannot create {}: {e}", dir.display());
            return ExitCode::from(EXIT_FAILED);
        }
        let mut emitter: Option<FrameEmitter> = None;
        rss.clear();
        let mut window_max = 0u64;
        let result = run_stream(graph, spec, &options, |frame| {
            if let (Some(dir), true) = (&args.emit, last_repeat) {
                let e = emitter.get_or_insert_with(|| {
                    FrameEmitter::for_stream(dir, spec, frame.total, frame.fps)
                });
                e.packet(frame)?;
            }
            if let Some(bytes) = current_rss_bytes() {
                window_max = window_max.max(bytes);
                if frame.position == 1 || frame.position.is_multiple_of(RSS_EVERY) {
                    rss.push((frame.position, window_max));
                    window_max = 0;
                }
            }
            if last_repeat {
                last_frame = Some((frame.packet.index, frame.outputs.clone()));
            }
            Ok(())
        });
        if let Some(bytes) = current_rss_bytes() {
            rss.push((usize::MAX, bytes));
        }
        let report = match result {
            Ok(r) => r,
            Err(e) => {
                eprintln!("error: {e}");
                // The emitter is dropped unfinished: its temp files go with it.
                return ExitCode::from(EXIT_FAILED);
            }
        };
        if let Some(e) = emitter {
            match e.finish() {
                Ok(files) => {
                    if let Some(dir) = &args.emit {
                        eprintln!("wrote {} files under {}", files.len(), dir.display());
                    }
                }
                Err(message) => {
                    eprintln!("error: {message}");
                    code = ExitCode::from(EXIT_FAILED);
                }
            }
        }
        if let (Some(dir), true) = (&args.emit, last_repeat) {
            for (name, value) in &report.outputs {
                if let Err(e) = ocellus_engine::emit::emit_value(dir, name, value) {
                    eprintln!("error: output `{name}`: {e}");
                    code = ExitCode::from(EXIT_FAILED);
                }
            }
        }
        reports.push(report);
    }
    let Some(last) = reports.last() else {
        return ExitCode::from(EXIT_INVALID);
    };
    if args.emit.is_none() {
        print!(
            "{}",
            ocellus_engine::summary::summarize_outputs(&last.outputs)
        );
        if let Some((index, outputs)) = &last_frame
            && !outputs.is_empty()
        {
            println!("# last frame ({index})");
            print!("{}", ocellus_engine::summary::summarize_outputs(outputs));
        }
    }
    let mut fps: Vec<f64> = reports.iter().map(StreamReport::fps).collect();
    fps.sort_by(f64::total_cmp);
    let median_fps = fps.get(fps.len() / 2).copied().unwrap_or(0.0);
    if let Some(path) = &args.profile
        && let Err(e) = write_profile(path, graph, last, threads, &rss, &fps)
    {
        eprintln!("error: cannot write profile {}: {e}", path.display());
        code = ExitCode::from(EXIT_FAILED);
    }
    let memory = rss_line(&rss);
    let repeats = if args.repeat > 1 {
        format!(
            "; median {median_fps:.1} frames/s over {} runs",
            args.repeat
        )
    } else {
        String::new()
    };
    let stages = last
        .stages
        .iter()
        .filter(|s| {
            matches!(
                s.class,
                ocellus_engine::stream::NodeClass::Source
                    | ocellus_engine::stream::NodeClass::PerFrame
                    | ocellus_engine::stream::NodeClass::Sequence
            )
        })
        .count();
    eprintln!(
        "streamed `{}` on {threads} thread{}: {}{repeats}; {stages} pipelined stages, capacity {}{memory}",
        graph.name,
        if threads == 1 { "" } else { "s" },
        last.summary_line(),
        spec.capacity,
    );
    code
}

fn rss_line(rss: &[(usize, u64)]) -> String {
    let at = |frame: usize| rss.iter().find(|(f, _)| *f == frame).map(|(_, b)| *b);
    let last = rss.last().map(|(_, b)| *b);
    match (at(RSS_EVERY), last) {
        (Some(a), Some(b)) => format!(
            "; resident {} at frame {RSS_EVERY}, {} at the end ({:+.1} %){}",
            render_bytes(a),
            render_bytes(b),
            (b as f64 / a as f64 - 1.0) * 100.0,
            window_range(rss, a)
        ),
        (None, Some(b)) => format!("; resident {} at the end", render_bytes(b)),
        _ => String::new(),
    }
}

/// `, per 100 frames from frame 100 on: −3.1 % to +4.0 %` (largest samples of each window
/// against the window ending at frame 100), when there are later windows.
fn window_range(rss: &[(usize, u64)], first: u64) -> String {
    let later: Vec<f64> = rss
        .iter()
        .filter(|(f, _)| *f > RSS_EVERY && *f != usize::MAX)
        .map(|(_, b)| (*b as f64 / first as f64 - 1.0) * 100.0)
        .collect();
    match (
        later.iter().copied().reduce(f64::min),
        later.iter().copied().reduce(f64::max),
    ) {
        (Some(lo), Some(hi)) => {
            format!(", per {RSS_EVERY} frames after frame {RSS_EVERY}: {lo:+.1} % to {hi:+.1} %")
        }
        _ => String::new(),
    }
}

fn write_profile(
    path: &Path,
    graph: &Graph,
    report: &StreamReport,
    threads: usize,
    rss: &[(usize, u64)],
    fps: &[f64],
) -> std::io::Result<()> {
    use serde_json::json;
    let stages: Vec<_> = report
        .stages
        .iter()
        .map(|s| {
            json!({
                "name": s.name,
                "op": s.op,
                "class": s.class.name(),
                "frames": s.frames,
                "busy_ms": s.busy.as_secs_f64() * 1e3,
            })
        })
        .collect();
    let memory: Vec<_> = rss
        .iter()
        .map(|(frame, bytes)| {
            json!({
                "frame": if *frame == usize::MAX { serde_json::Value::from("end") } else { serde_json::Value::from(*frame) },
                "resident_bytes": bytes,
            })
        })
        .collect();
    let value = json!({
        "graph": graph.name,
        "threads": threads,
        "frames": report.completed,
        "dropped": report.dropped,
        "unaligned": report.unaligned,
        "elapsed_ms": report.elapsed.as_secs_f64() * 1e3,
        "frames_per_s": report.fps(),
        "frames_per_s_runs": fps,
        "max_lateness_ms": report.max_lateness.as_secs_f64() * 1e3,
        "resident": memory,
        "stages": stages,
    });
    let text = serde_json::to_string_pretty(&value).map_err(std::io::Error::other)?;
    ocellus_engine::image_io::write_atomic(path, text.as_bytes())
}
