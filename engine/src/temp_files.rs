//! The temp files of writes in flight, so that an interrupted run leaves only complete files.
//!
//! Every output is written to a hidden temp file beside its target and renamed over it when
//! complete ([`crate::image_io::write_atomic_with`], the animation and JSON-lines writers), so a
//! reader never sees a partial file under the target's name. What an interruption could leave is
//! the temp file itself. Each one is created through [`create`], which records it, and dropped
//! from the record by [`forget`] once renamed or removed. On SIGINT/SIGTERM the CLI calls
//! [`remove_all_and_exit`]: it closes the record (a write that starts afterwards fails instead of
//! creating a file), removes every recorded temp file and ends the process. A rename racing with
//! that removal either completed — the target is whole — or finds its temp file gone and changes
//! nothing.
//!
//! A process killed outright (SIGKILL, power loss) cannot clean up; its temp files are named
//! `.{target}.{pid}.{n}.tmp` (or `.part`), and [`sweep_stale`] removes those whose process is
//! gone the next time a run writes into the folder.

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

/// Creates a new temp file (it must not exist) and records it. Fails with
/// [`io::ErrorKind::Interrupted`] once the process is shutting down (not reachable in practice:
/// [`remove_all_and_exit`] keeps the record locked until the process is gone).
pub fn create(path: &Path) -> io::Result<File> {
    let mut record = record();
    if record.closed {
        return Err(io::Error::new(
            io::ErrorKind::Interrupted,
            "the run was interrupted",
        ));
    }
    let file = OpenOptions::new().write(true).create_new(true).open(path)?;
    record.paths.insert(path.to_path_buf());
    Ok(file)
}

/// Drops a temp file from the record after it was renamed or removed.
pub fn forget(path: &Path) {
    record().paths.remove(path);
}

/// Temp files currently recorded.
pub fn in_flight() -> usize {
    record().paths.len()
}

/// Closes the record, removes every temp file in it and exits with `code`. Called from the
/// CLI's signal thread. The lock is held until the process ends, so no temp file can be created
/// after the sweep (a writer that tries blocks, then ends with the process).
pub fn remove_all_and_exit(code: i32) -> ! {
    let mut record = record();
    record.closed = true;
    for path in std::mem::take(&mut record.paths) {
        let _ = std::fs::remove_file(&path);
    }
    std::process::exit(code)
}

/// The process id in a temp file name `.{target}.{pid}.{n}.tmp` / `.part` (also the JSON-lines
/// form `.{target}.{pid}.part`), if it is one.
fn temp_owner(name: &str) -> Option<u32> {
    if !name.starts_with('.') {
        return None;
    }
    let stem = name
        .strip_suffix(".tmp")
        .or_else(|| name.strip_suffix(".part"))?;
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
        assert_eq!(temp_owner(".out.png.1234.7.tmp"), Some(1234));
        assert_eq!(temp_owner(".walk.gif.99.0.part"), Some(99));
        assert_eq!(temp_owner(".metrics.jsonl.4321.part"), Some(4321));
        assert_eq!(temp_owner("out.png.1234.7.tmp"), None);
        assert_eq!(temp_owner(".hidden"), None);
        assert_eq!(temp_owner(".a.b.tmp"), None);
    }

    #[test]
    fn stale_temp_files_of_dead_processes_are_swept_and_live_ones_kept() {
        let dir = std::env::temp_dir().join(format!("ocellus-temp-files-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        // A pid above the kernel's maximum (2^22) cannot be running.
        let dead = dir.join(".a.png.4194305.0.tmp");
        let live = dir.join(format!(".b.png.{}.0.tmp", std::process::id()));
        let target = dir.join("a.png");
        for p in [&dead, &live, &target] {
            std::fs::write(p, b"x").unwrap();
        }
        let removed = sweep_stale(&dir);
        if Path::new("/proc/self").exists() {
            assert_eq!(removed, 1);
            assert!(!dead.exists());
        }
        assert!(live.exists() && target.exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
