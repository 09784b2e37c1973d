//! `ocellus`: run, check and inspect Ocellus graphs.

mod animation;
mod cli;
mod ops;
mod plot;
mod profile;
mod ray;
mod report;
mod run_report;
mod streaming;
mod sweep;

use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    // Operator panics are caught by the scheduler and reported as node errors; the default hook
    // would print a second, raw message (and a backtrace hint) for each.
    std::panic::set_hook(Box::new(|_| {}));
    // Operators allocate megabytes of levels and intermediates per call: keep freed blocks
    // for the next call instead of faulting fresh pages in every time.
    ocellus_engine::buffer::keep_freed_memory();
    let args = cli::Cli::parse();
    init_tracing(args.verbose);
    remove_partial_files_on_interrupt();
    match std::panic::catch_unwind(|| cli::dispatch(args)) {
        Ok(code) => code,
        Err(payload) => {
            let message = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".into());
            eprintln!("error: internal error: {message}\nplease report this as a bug");
            ExitCode::from(70)
        }
    }
}

/// On SIGINT, SIGTERM or SIGHUP, removes the temp files of the writes in flight, then ends the
/// process by that signal: outputs already renamed into place are complete, and nothing partial
/// is left (see `ocellus_engine::temp_files`).
fn remove_partial_files_on_interrupt() {
    #[cfg(unix)]
    {
        use signal_hook::consts::{SIGHUP, SIGINT, SIGTERM};
        let Ok(mut signals) = signal_hook::iterator::Signals::new([SIGINT, SIGTERM, SIGHUP]) else {
            tracing::warn!(
                "cannot install signal handlers; an interrupted run may leave temp files"
            );
            return;
        };
        let spawned = std::thread::Builder::new()
            .name("signals".into())
            .spawn(move || {
                if let Some(signal) = signals.forever().next() {
                    eprintln!("\ninterrupted (signal {signal}); removing partial files");
                    let _closed = ocellus_engine::temp_files::close_and_remove_all();
                    // End by the signal itself, so a shell loop or `make` sees an interrupted
                    // child and stops too; exit 128 + signal where that is impossible.
                    let _ = signal_hook::low_level::emulate_default_handler(signal);
                    std::process::exit(128 + signal);
                }
            });
        if spawned.is_err() {
            tracing::warn!(
                "cannot start the signal thread; an interrupted run may leave temp files"
            );
        }
    }
}

fn init_tracing(verbose: u8) {
    let level = match verbose {
        0 => "warn",
        1 => "info",
        2 => "debug",
        _ => "trace",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_env("OCELLUS_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(level));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}
