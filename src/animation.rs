//! `ocellus run` on a graph with an `animation` section: one run per frame, outputs emitted as
//! frame folders, GIF/APNG and CSV (see `ocellus_engine::sequence_write::FrameEmitter`).

use std::path::Path;
use std::process::ExitCode;
use std::sync::Arc;

use ocellus_engine::cache::MemoryCache;
use ocellus_engine::sequence_write::FrameEmitter;
use ocellus_engine::timeline::{Animated, run_timeline};
use ocellus_engine::{Graph, Registry, RunOptions, RunReport};

use crate::cli::{EXIT_FAILED, EXIT_INVALID, RunArgs};
use crate::profile::Profile;
use crate::report::render_bytes;

/// Runs every frame of `animated` (`--repeat` times), emitting the last repeat's frames.
pub fn run_animated(
    registry: &Registry,
    args: &RunArgs,
    graph: &Graph,
    animated: &Animated,
    threads: usize,
) -> ExitCode {
    let mut code = ExitCode::SUCCESS;
    let mut frame_reports: Vec<RunReport> = Vec::new();
    let mut last_outputs = None;
    let mut wall = Vec::new();
    let mut summary = None;
    for repeat in 0..args.repeat {
        let last_repeat = repeat + 1 == args.repeat;
        let options = RunOptions {
            // A fresh cache per repeat: `--repeat` times whole animations.
            memory_cache: Some(Arc::new(MemoryCache::new())),
            ..args.options(threads)
        };
        let mut emitter = match (&args.emit, last_repeat) {
            (Some(dir), true) => {
                if let Err(e) = ocellus_engine::temp_files::prepare_dir(dir) {
                    eprintln!("error: cannot create {}: {e}", dir.display());
                    return ExitCode::from(EXIT_FAILED);
                }
                Some(FrameEmitter::new(dir, animated))
            }
            _ => None,
        };
        let mut failures = Vec::new();
        let mut emit_errors = Vec::new();
        frame_reports.clear();
        let result = run_timeline(registry, animated, &options, |frame| {
            for f in &frame.report.failures {
                failures.push(format!("frame {}: {f}", frame.frame));
            }
            if let Some(e) = emitter.as_mut()
                && let Err(message) = e.frame(&frame)
            {
                emit_errors.push(message);
            }
            if frame.index + 1 == animated.frames {
                last_outputs = Some(frame.report.outputs.clone());
            }
            let failed = !frame.report.failures.is_empty();
            frame_reports.push(frame.report);
            // A node that failed in this frame fails in the next ones too (or it would have
            // been the same node): stop at the first failing frame.
            if failed {
                Err("stopped".into())
            } else {
                Ok(())
            }
        });
        let report = match result {
            Ok(r) => r,
            Err(_) if !failures.is_empty() => {
                for f in &failures {
                    eprintln!("error: {f}");
                }
                eprintln!("error: the animation stopped at the first frame that failed");
                return ExitCode::from(EXIT_FAILED);
            }
            Err(e) => {
                eprintln!("error: {e}");
                return ExitCode::from(EXIT_INVALID);
            }
        };
        wall.push(report.elapsed.as_secs_f64() * 1e3);
        if last_repeat {
            for f in &failures {
                eprintln!("error: {f}");
            }
            if !failures.is_empty() {
                code = ExitCode::from(EXIT_FAILED);
            }
            if let Some(e) = emitter {
                match e.finish() {
                    Ok(files) => {
                        if let Some(dir) = &args.emit {
                            eprintln!("wrote {} files under {}", files.len(), dir.display());
                        }
                    }
                    Err(message) => emit_errors.push(message),
                }
            }
            for e in &emit_errors {
                eprintln!("error: {e}");
            }
            if !emit_errors.is_empty() {
                code = ExitCode::from(EXIT_FAILED);
            }
            summary = Some(report);
        }
    }
    if args.emit.is_none()
        && let Some(outputs) = &last_outputs
    {
        println!("# last frame ({})", animated.frames - 1);
        print!("{}", ocellus_engine::summary::summarize_outputs(outputs));
    }
    if let Some(path) = &args.profile {
        // Each frame of the last repeat is one run of the profile.
        let profile = Profile::from_reports(&frame_reports);
        if let Err(e) = profile.write(path) {
            eprintln!("error: cannot write profile {}: {e}", path.display());
            code = ExitCode::from(EXIT_FAILED);
        }
    }
    let Some(summary) = summary else {
        return ExitCode::from(EXIT_INVALID);
    };
    wall.sort_by(f64::total_cmp);
    let median = wall.get(wall.len() / 2).copied().unwrap_or(0.0);
    let timing = if args.repeat > 1 {
        format!("median {median:.2} ms over {} runs", args.repeat)
    } else {
        format!("{median:.2} ms")
    };
    let peak = frame_reports
        .iter()
        .map(|r| r.peak_bytes)
        .max()
        .unwrap_or(0);
    eprintln!(
        "ran `{}` over {} frames at {} fps in {timing} on {threads} thread{}: {} nodes — {} computed, {} reused across frames; peak outputs {}",
        graph.name,
        summary.frames,
        animated.fps,
        if threads == 1 { "" } else { "s" },
        graph.nodes.len(),
        summary.computed,
        summary.cached,
        render_bytes(peak as u64),
    );
    code
}

/// The timeline of a graph file, if it has one (the file was already loaded once, so errors
/// here are the timeline's own).
pub fn timeline(
    registry: &Registry,
    path: &Path,
    set: &[String],
) -> Result<Option<Animated>, ocellus_engine::Diagnostics> {
    let overrides = parse_overrides(set)?;
    ocellus_engine::timeline::load_animated_file(registry, path, &overrides).map(|(_, a)| a)
}

/// `--set` values, or the first malformed one's diagnostic.
pub fn parse_overrides(
    set: &[String],
) -> Result<Vec<ocellus_engine::Override>, ocellus_engine::Diagnostics> {
    set.iter()
        .map(|arg| {
            ocellus_engine::Override::parse(arg).map_err(|d| ocellus_engine::Diagnostics(vec![*d]))
        })
        .collect()
}
