//! Resource limits on what a run reads and builds, so that a hostile or mistaken input — a PNG
//! header claiming 20,000² pixels, a PLY claiming 10⁹ vertices, a 50 GB file, a device that never
//! ends — is a clear error instead of an out-of-memory kill.
//!
//! The limits are process-wide: the CLI sets them once from `--max-image-pixels`,
//! `--max-alloc-bytes` and `--max-list-len` before any graph runs, and every reader consults
//! them. Each reader also refuses, before allocating, a count its file is too short to hold, so
//! memory stays proportional to the bytes actually read.

use std::io::{self, Read};
use std::path::Path;
use std::sync::RwLock;

/// The limits of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Largest image accepted by a decoder, in pixels (`width × height`), checked against the
    /// header before any pixel is decoded (`--max-image-pixels`).
    pub max_image_pixels: u64,
    /// Largest input file read, and largest decoded image buffer, in bytes
    /// (`--max-alloc-bytes`).
    pub max_alloc_bytes: u64,
    /// Most elements a file may declare (vertices, faces, points, observations) and a node may
    /// output in one list (`--max-list-len`).
    pub max_list_len: u64,
}

impl Limits {
    /// Default pixel limit: 2²⁸ ≈ 268 M pixels (16384 × 16384).
    pub const DEFAULT_MAX_IMAGE_PIXELS: u64 = 1 << 28;
    /// Default byte limit: 4 GiB.
    pub const DEFAULT_MAX_ALLOC_BYTES: u64 = 4 << 30;
    /// Default list limit: 2²⁸ ≈ 268 M elements.
    pub const DEFAULT_MAX_LIST_LEN: u64 = 1 << 28;
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_image_pixels: Self::DEFAULT_MAX_IMAGE_PIXELS,
            max_alloc_bytes: Self::DEFAULT_MAX_ALLOC_BYTES,
            max_list_len: Self::DEFAULT_MAX_LIST_LEN,
        }
    }
}

static LIMITS: RwLock<Limits> = RwLock::new(Limits {
    max_image_pixels: Limits::DEFAULT_MAX_IMAGE_PIXELS,
    max_alloc_bytes: Limits::DEFAULT_MAX_ALLOC_BYTES,
    max_list_len: Limits::DEFAULT_MAX_LIST_LEN,
});

/// Sets the process-wide limits (the CLI does, once, before running anything).
pub fn set(limits: Limits) {
    *LIMITS.write().unwrap_or_else(|p| p.into_inner()) = limits;
}

/// The process-wide limits.
pub fn get() -> Limits {
    *LIMITS.read().unwrap_or_else(|p| p.into_inner())
}

/// Reads a whole file, refusing one over [`Limits::max_alloc_bytes`]; see [`read_capped`].
pub fn read_file(path: &Path) -> io::Result<Vec<u8>> {
    read_capped(path, get().max_alloc_bytes, "--max-alloc-bytes")
}

/// Reads a whole file of at most `limit` bytes — checked by its size before reading, and by
/// what was read for devices and pipes, which report no size (`/dev/zero` would otherwise never
/// end). The error names `source`, where the limit comes from.
pub fn read_capped(path: &Path, limit: u64, source: &str) -> io::Result<Vec<u8>> {
    let file = std::fs::File::open(path)?;
    let declared = file.metadata().map(|m| m.len()).unwrap_or(0);
    if declared > limit {
        return Err(too_large(declared, limit, source));
    }
    let capacity = usize::try_from(declared).unwrap_or(0);
    let mut bytes = Vec::with_capacity(capacity);
    file.take(limit.saturating_add(1)).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > limit {
        return Err(too_large(bytes.len() as u64, limit, source));
    }
    Ok(bytes)
}

/// [`read_file`] as UTF-8 text.
pub fn read_text(path: &Path) -> io::Result<String> {
    String::from_utf8(read_file(path)?).map_err(|e| {
        io::Error::new(
            io::ErrorKind::InvalidData,
            format!(
                "not UTF-8 text (invalid byte at offset {})",
                e.utf8_error().valid_up_to()
            ),
        )
    })
}

fn too_large(bytes: u64, limit: u64, source: &str) -> io::Error {
    io::Error::new(
        io::ErrorKind::FileTooLarge,
        format!("the file is {bytes} bytes, over the limit of {limit} ({source})"),
    )
}

/// Checks a count a file declares (or a list a node built) against [`Limits::max_list_len`];
/// the error names `what`.
pub fn check_count(what: &str, count: u64) -> Result<(), String> {
    let limit = get().max_list_len;
    if count > limit {
        Err(format!(
            "{count} {what}, over the limit of {limit} (--max-list-len)"
        ))
    } else {
        Ok(())
    }
}

/// Parses a byte count: a number with an optional binary suffix `K`, `M`, `G` or `T` (`KiB`,
/// `MiB`… and `KB`, `MB`… mean the same), as `--max-alloc-bytes` takes it.
pub fn parse_bytes(text: &str) -> Result<u64, String> {
    let t = text.trim();
    let digits_end = t.find(|c: char| !c.is_ascii_digit()).unwrap_or(t.len());
    let (number, suffix) = t.split_at(digits_end);
    let value: u64 = number
        .parse()
        .map_err(|_| format!("`{text}` is not a byte count (like 4096, 512M or 4G)"))?;
    let shift = match suffix.trim().to_ascii_uppercase().as_str() {
        "" | "B" => 0,
        "K" | "KB" | "KIB" => 10,
        "M" | "MB" | "MIB" => 20,
        "G" | "GB" | "GIB" => 30,
        "T" | "TB" | "TIB" => 40,
        _ => {
            return Err(format!(
                "`{text}`: unknown unit `{suffix}` (use K, M, G or T)"
            ));
        }
    };
    value
        .checked_mul(1u64 << shift)
        .ok_or_else(|| format!("`{text}` does not fit in 64 bits"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn byte_counts_parse_with_binary_units() {
        assert_eq!(parse_bytes("4096"), Ok(4096));
        assert_eq!(parse_bytes("512M"), Ok(512 << 20));
        assert_eq!(parse_bytes("4G"), Ok(4 << 30));
        assert_eq!(parse_bytes("2 GiB"), Ok(2 << 30));
        assert_eq!(parse_bytes("1k"), Ok(1024));
        assert!(parse_bytes("").is_err());
        assert!(parse_bytes("-1").is_err());
        assert!(parse_bytes("3X").is_err());
        assert!(parse_bytes("99999999999T").is_err());
    }

    #[test]
    fn a_device_that_reports_no_size_stops_at_the_cap() {
        let zero = Path::new("/dev/zero");
        if !zero.exists() {
            return;
        }
        let err = read_capped(zero, 1024, "test cap").unwrap_err();
        assert!(
            err.to_string()
                .contains("over the limit of 1024 (test cap)"),
            "{err}"
        );
        // The graph loader (and so an include naming a device) goes through the same cap.
        let diagnostic = crate::resolve::read_source(zero, "zero.ron").unwrap_err();
        assert!(
            diagnostic.message.contains("graph files"),
            "{}",
            diagnostic.message
        );
    }

    #[test]
    fn read_file_returns_the_bytes_and_read_text_refuses_non_utf8() {
        // The cap itself (a device reporting no size, a file over the limit) is checked through
        // the CLI in tests/limits.rs: the limits are process-wide, and lowering them here would
        // race with the other tests of this binary.
        let dir = std::env::temp_dir().join(format!("ocellus-limits-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("small.bin");
        std::fs::write(&path, b"abc").unwrap();
        assert_eq!(read_file(&path).unwrap(), b"abc");
        assert!(read_text(&path).is_ok());
        std::fs::write(&path, [0xff, 0xfe]).unwrap();
        assert!(read_text(&path).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
