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
/// frames — the mean and the largest of its samples — plus once at the end. Not a single
/// sample: how many packets sit in the channels when a frame reaches the sink varies from
/// frame to frame, and with it the resident size by tens of megabytes. The window mean is what
/// shows growth (it is steady when memory is); the largest sample is the bound.
const RSS_EVERY: usize = 100;

/// The resident set size over one window of frames.
#[derive(Debug, Clone, Copy)]
struct RssWindow {
    /// Last frame of the window (`usize::MAX`: after the stream).
    frame: usize,
    /// Mean of the per-frame samples, bytes.
    mean: u64,
    /// Largest sample, bytes.
    max: u64,
    /// Median of the per-frame samples, bytes.
    median: u64,
}

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

/// Frame-sized buffers (this many bytes and more) get a mapping of their own from the
/// allocator, returned to the OS when they are freed.
const FRAME_BUFFER_BYTES: usize = 1 << 20;

/// Sets the allocator up for a stream on two or more threads: frame-sized buffers mapped on
/// their own ([`FRAME_BUFFER_BYTES`]), so that the resident size follows the frames in flight.
///
/// glibc raises its `mmap` threshold each time a mapped buffer is freed, so after the first
/// frames every frame buffer comes from the heaps instead. With several workers, buffers are
/// allocated and freed on several threads in an order that timing decides, and the heaps keep
/// the pages of the holes this leaves: over 1000 frames of `graphs/track.ron` at 2 threads the
/// window medians rose by 13–20 % over the first 500 frames before levelling off. A fixed
/// threshold of 1 MiB keeps them within ±7 %, at no measurable cost in frames/s at 2 threads
/// (paired 200-frame runs, ratio 0.99; 2.6 s more system time). On one thread the heaps are reused in a
/// steady order and stay flat without it (−0.8 % to +3.4 %), while the zeroing would cost 10 %
/// of the run time, so one thread keeps the CLI's settings (`buffer::keep_freed_memory`: a
/// fixed 32 MiB threshold, under which frame buffers come from the heaps as they did under
/// glibc's raised default; the figures above were measured under that default, before the CLI
/// fixed it). A threshold of 4 MiB leaves the
/// 2.8 MB colour frames and 3.7 MB float planes in the heaps and does not stop the rise.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn fix_mmap_threshold() {
    let bytes = libc::c_int::try_from(FRAME_BUFFER_BYTES).unwrap_or(libc::c_int::MAX);
    // SAFETY: `mallopt` only changes a setting of the allocator, under its own lock; it is
    // safe to call at any time, and a refusal (0) leaves the default behaviour.
    #[allow(unsafe_code)]
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, bytes);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn fix_mmap_threshold() {}

/// Hands the allocator's free pages back to the OS (once per window of frames): the small
/// buffers below [`FRAME_BUFFER_BYTES`] still come from the heaps, and a trim returns the
/// pages of their holes. It costs no measurable time once per window.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn trim_allocator() {
    // SAFETY: `malloc_trim` only releases free memory inside the allocator, under its own
    // locks; it reads no pointer of ours and is safe to call from any thread at any time.
    #[allow(unsafe_code)]
    unsafe {
        libc::malloc_trim(0);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn trim_allocator() {}

/// Streams `graph` (`--repeat` times), emitting the last repeat's frames.
pub fn run_streamed(args: &RunArgs, graph: &Graph, spec: &StreamSpec, threads: usize) -> ExitCode {
    let mut reports: Vec<StreamReport> = Vec::new();
    let mut rss: Vec<RssWindow> = Vec::new();
    let mut last_frame: Option<(usize, Vec<(String, Value)>)> = None;
    let mut code = ExitCode::SUCCESS;
    if threads >= 2 {
        fix_mmap_threshold();
    }
    for repeat in 0..args.repeat {
        let last_repeat = repeat + 1 == args.repeat;
        let options = args.options(threads);
        if let (Some(dir), true) = (&args.emit, last_repeat)
            && let Err(e) = ocellus_engine::temp_files::prepare_dir(dir)
        {
            eprintln!("error: cannot create {}: {e}", dir.display());
            return ExitCode::from(EXIT_FAILED);
        }
        let mut emitter: Option<FrameEmitter> = None;
        rss.clear();
        let (mut window_max, mut window_sum, mut window_n) = (0u64, 0u64, 0u64);
        let mut window_samples: Vec<u64> = Vec::with_capacity(RSS_EVERY);
        let result = run_stream(graph, spec, &options, |frame| {
            if let (Some(dir), true) = (&args.emit, last_repeat) {
                let e = emitter.get_or_insert_with(|| {
                    FrameEmitter::for_stream(dir, spec, frame.total, frame.fps)
                });
                e.packet(frame)?;
            }
            if let Some(bytes) = current_rss_bytes() {
                window_max = window_max.max(bytes);
                window_sum += bytes;
                window_n += 1;
                window_samples.push(bytes);
                if frame.position == 1 || frame.position.is_multiple_of(RSS_EVERY) {
                    window_samples.sort_unstable();
                    rss.push(RssWindow {
                        frame: frame.position,
                        mean: window_sum / window_n,
                        max: window_max,
                        median: window_samples[window_samples.len() / 2],
                    });
                    window_samples.clear();
                    trim_allocator();
                    (window_max, window_sum, window_n) = (0, 0, 0);
                }
            }
            if last_repeat {
                last_frame = Some((frame.packet.index, frame.outputs.clone()));
            }
            Ok(())
        });
        if let Some(bytes) = current_rss_bytes() {
            rss.push(RssWindow {
                frame: usize::MAX,
                mean: bytes,
                max: bytes,
                median: bytes,
            });
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

fn rss_line(rss: &[RssWindow]) -> String {
    let first = rss.iter().find(|w| w.frame == RSS_EVERY);
    let last = rss.last().map(|w| w.max);
    match (first, last) {
        (Some(first), Some(end)) => format!(
            "; resident {} (mean of frames 2–{RSS_EVERY}; largest {}), {} at the end{}",
            render_bytes(first.mean),
            render_bytes(first.max),
            render_bytes(end),
            window_range(rss, first)
        ),
        (None, Some(end)) => format!("; resident {} at the end", render_bytes(end)),
        _ => String::new(),
    }
}

/// `; later windows of 100 frames: mean −3.1 % to +4.0 %, largest 120.3 MB` (against the
/// window ending at frame 100), when there are later windows.
fn window_range(rss: &[RssWindow], first: &RssWindow) -> String {
    let later: Vec<&RssWindow> = rss
        .iter()
        .filter(|w| w.frame > RSS_EVERY && w.frame != usize::MAX)
        .collect();
    let change = |w: &&RssWindow| (w.mean as f64 / first.mean as f64 - 1.0) * 100.0;
    match (
        later.iter().map(change).reduce(f64::min),
        later.iter().map(change).reduce(f64::max),
        later.iter().map(|w| w.max).max(),
    ) {
        (Some(lo), Some(hi), Some(max)) => format!(
            "; later windows of {RSS_EVERY} frames: mean {lo:+.1} % to {hi:+.1} %, largest {}",
            render_bytes(max)
        ),
        _ => String::new(),
    }
}

fn write_profile(
    path: &Path,
    graph: &Graph,
    report: &StreamReport,
    threads: usize,
    rss: &[RssWindow],
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
        .map(|w| {
            json!({
                "frame": if w.frame == usize::MAX { serde_json::Value::from("end") } else { serde_json::Value::from(w.frame) },
                "mean_resident_bytes": w.mean,
                "max_resident_bytes": w.max,
                "median_resident_bytes": w.median,
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
