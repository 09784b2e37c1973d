//! The temp files of writes in flight, so that an interrupted run leaves only complete files.
//!
//! Every output is written to a hidden temp file beside its target and renamed over it when
//! complete ([`crate::image_io::write_atomic_with`], the animation and JSON-lines writers), so a
//! reader never sees a partial file under the target's name. What an interruption could leave is
//! the temp file itself. Each one is created through [`create`], which records it, and dropped
//! from the record by [`forget`] once renamed or removed. On SIGINT, SIGTERM or SIGHUP the CLI
//! calls [`close_and_remove_all`]: it closes the record (a write that starts afterwards blocks,
//! then ends with the process), removes every recorded temp file, and the CLI then ends the
//! process by the signal. A rename racing with that removal either completed — the target is
//! whole — or finds its temp file gone and changes nothing.
//!
//! A process killed outright (SIGKILL, power loss) cannot clean up; its temp files are named
//! `.{target}.{pid}.{n}.ocellus.tmp` (`.{target}.{pid}.{n}.ocellus.part` for animations,
//! `.{target}.{pid}.ocellus.part` for JSON lines), and [`sweep_stale`] removes those whose
//! process is gone the next time a run writes into the folder. Only names with the `.ocellus.`
//! marker are considered, and liveness is judged on this host: a folder shared between machines
//! (NFS) should not be written by runs on several hosts at once.

use std::collections::BTreeSet;
use std::fs::{File, OpenOptions};
use std::io;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};

struct Record {
    paths: BTreeSet<PathBuf>,
    closed: bool,
}

static RECORD: Mutex<Record> = Mutex::new(Record {
    paths: BTreeSet::new(),
    closed: false,
});

fn record() -> MutexGuard<'static, Record> {
    // A panic while holding the lock cannot leave the set inconsistent (single insert/remove).
    RECORD
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// Creates a new temp file (it must not exist) and records it. Fails once the process is
/// shutting down (not reachable in practice: [`close_and_remove_all`]'s guard keeps the record
/// locked until the process is gone).
pub fn create(path: &Path) -> io::Result<File> {
    let mut record = record();
    if record.closed {
        return Err(io::Error::other("the run was interrupted"));
    }
    let file = OpenOptions::new().write(true).create_new(true).open(path)?;
    record.paths.insert(path.to_path_buf());
    Ok(file)
}

/// Drops a temp file from the record after it was renamed or removed.
pub fn forget(path: &Path) {
    record().paths.remove(path);
}

/// The record, closed and locked: while this lives no temp file can be created or renamed.
/// Hold it until the process has ended.
pub struct ClosedRecord {
    _guard: MutexGuard<'static, Record>,
}

/// Closes the record and removes every temp file in it; returns the record still locked, so no
/// temp file can be created after the sweep (a writer that tries blocks, then ends with the
/// process). Called from the CLI's signal thread, which then ends the process.
pub fn close_and_remove_all() -> ClosedRecord {
    let mut record = record();
    record.closed = true;
    for path in std::mem::take(&mut record.paths) {
        let _ = std::fs::remove_file(&path);
    }
    ClosedRecord { _guard: record }
}

/// The process id in a temp file name `.{target}.{pid}.{n}.ocellus.tmp` / `.ocellus.part` (also
/// the JSON-lines form `.{target}.{pid}.ocellus.part`), if it is one of ours.
fn temp_owner(name: &str) -> Option<u32> {
    if !name.starts_with('.') {
        return None;
    }
    let stem = name
        .strip_suffix(".ocellus.tmp")
        .or_else(|| name.strip_suffix(".ocellus.part"))?;
    let mut fields = stem.rsplit('.');
    let last = fields.next()?;
    let before = fields.next()?;
    // `.{target}.{pid}.{n}`: the pid is the second-last field; `.{target}.{pid}`: the last.
    match (before.parse::<u32>(), last.parse::<u64>()) {
        (Ok(pid), Ok(_)) => Some(pid),
        (Err(_), Ok(_)) => last.parse().ok(),
        _ => None,
    }
}

/// Whether a process is alive, where the platform lets us tell cheaply (Linux `/proc`);
/// elsewhere every process counts as alive and nothing is swept.
fn process_alive(pid: u32) -> bool {
    if pid == std::process::id() {
        return true;
    }
    let proc_root = Path::new("/proc");
    if !proc_root.join("self").exists() {
        return true;
    }
    proc_root.join(pid.to_string()).exists()
}

/// Removes the temp files in `dir` left by processes that no longer run (a run killed outright);
/// returns how many. Temp files of live processes — a concurrent run writing into the same
/// folder — are left alone.
pub fn sweep_stale(dir: &Path) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    let mut removed = 0;
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(pid) = temp_owner(&name.to_string_lossy()) else {
            continue;
        };
        let is_file = entry.file_type().is_ok_and(|t| t.is_file());
        if is_file && !process_alive(pid) && std::fs::remove_file(entry.path()).is_ok() {
            removed += 1;
        }
    }
    removed
}

/// Creates `dir` (and its parents) if needed and sweeps the stale temp files in it: what every
/// writer calls on the folder it writes into.
pub fn prepare_dir(dir: &Path) -> io::Result<()> {
    std::fs::create_dir_all(dir)?;
    sweep_stale(dir);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn temp_names_give_their_owner() {
        assert_eq!(temp_owner(".out.png.1234.7.ocellus.tmp"), Some(1234));
        assert_eq!(temp_owner(".walk.gif.99.0.ocellus.part"), Some(99));
        assert_eq!(temp_owner(".metrics.jsonl.4321.ocellus.part"), Some(4321));
        assert_eq!(temp_owner("out.png.1234.7.ocellus.tmp"), None);
        assert_eq!(temp_owner(".hidden"), None);
        assert_eq!(temp_owner(".a.b.ocellus.tmp"), None);
        // Another program's temp files, even shaped like ours, are not ours.
        assert_eq!(temp_owner(".x.12345.tmp"), None);
        assert_eq!(temp_owner(".out.png.1234.7.tmp"), None);
    }

    #[test]
    fn stale_temp_files_of_dead_processes_are_swept_and_live_ones_kept() {
        let dir = std::env::temp_dir().join(format!("ocellus-temp-files-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        // A pid above the kernel's maximum (2^22) cannot be running.
        let dead = dir.join(".a.png.4194305.0.ocellus.tmp");
        let live = dir.join(format!(".b.png.{}.0.ocellus.tmp", std::process::id()));
        let foreign = dir.join(".c.4194305.tmp");
        let target = dir.join("a.png");
        for p in [&dead, &live, &foreign, &target] {
            std::fs::write(p, b"x").unwrap();
        }
        let removed = sweep_stale(&dir);
        if Path::new("/proc/self").exists() {
            assert_eq!(removed, 1);
            assert!(!dead.exists());
        }
        assert!(live.exists() && foreign.exists() && target.exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
