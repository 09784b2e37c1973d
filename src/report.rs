//! Rendering for people: diagnostics with source snippets, byte sizes, process memory.

use std::io::IsTerminal;
use std::path::Path;

use ocellus_engine::Diagnostics;

/// Prints every diagnostic (file:line:col, snippet, caret, hint) and a closing count to stderr.
pub fn print_diagnostics(diags: &Diagnostics, graph: &Path) {
    let theme = if std::io::stderr().is_terminal() {
        miette::GraphicalTheme::unicode()
    } else {
        miette::GraphicalTheme::unicode_nocolor()
    };
    let handler = miette::GraphicalReportHandler::new_themed(theme).with_context_lines(1);
    for d in &diags.0 {
        let mut out = String::new();
        if handler.render_report(&mut out, d).is_err() {
            out = format!("{}: {}\n", d.location().unwrap_or_default(), d.message);
        }
        eprint!("{out}");
    }
    let n = diags.len();
    eprintln!(
        "error: {n} problem{} found in {}",
        if n == 1 { "" } else { "s" },
        graph.display()
    );
}

/// `12.3 MB`-style sizes (decimal units).
pub fn render_bytes(bytes: u64) -> String {
    const UNITS: [&str; 5] = ["B", "kB", "MB", "GB", "TB"];
    let mut value = bytes as f64;
    let mut unit = 0;
    while value >= 1000.0 && unit < UNITS.len() - 1 {
        value /= 1000.0;
        unit += 1;
    }
    if unit == 0 {
        format!("{bytes} B")
    } else {
        format!("{value:.1} {}", UNITS[unit])
    }
}

/// The process's peak resident set size, where the OS reports it (Linux `VmHWM`).
pub fn peak_rss_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

#[cfg(test)]
mod tests {
    use super::render_bytes;

    #[test]
    fn byte_sizes() {
        assert_eq!(render_bytes(999), "999 B");
        assert_eq!(render_bytes(1500), "1.5 kB");
        assert_eq!(render_bytes(6_220_800), "6.2 MB");
    }
}
