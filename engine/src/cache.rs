//! The persistent result cache: one file per node result, named by the node's content key, so a
//! re-run after changing one parameter recomputes only what is downstream of it.
//!
//! Files are written atomically (temp file + rename), so concurrent runs sharing a folder and runs
//! killed mid-write never leave a torn entry. Each file is [`ENTRY_MAGIC`], the BLAKE3 hash of
//! the payload, then the payload (the value codec); a read verifies the hash before decoding, so
//! a file damaged on disk, truncated by a full disk or written by something else is ignored and
//! the result recomputed (and stored again), never decoded into a wrong value.

use std::path::{Path, PathBuf};

use crate::codec::{decode_values, encode_values};
use crate::types::PortType;
use crate::value::Value;

/// A cache folder.
#[derive(Debug, Clone)]
pub struct DiskCache {
    dir: PathBuf,
}

impl DiskCache {
    /// Opens (creating if needed) a cache folder.
    pub fn open(dir: &Path) -> std::io::Result<DiskCache> {
        crate::temp_files::prepare_dir(dir)?;
        Ok(DiskCache {
            dir: dir.to_path_buf(),
        })
    }

    /// The file holding a key's result.
    pub fn path(&self, key: &[u8; 32]) -> PathBuf {
        let hex: String = key.iter().map(|b| format!("{b:02x}")).collect();
        self.dir.join(format!("{hex}.ocv"))
    }

    /// The stored result for `key`, if present, intact (its hash verifies) and of the expected
    /// types.
    pub fn load(&self, key: &[u8; 32], types: &[PortType]) -> Option<Vec<Value>> {
        let bytes = std::fs::read(self.path(key)).ok()?;
        let payload = verified_payload(&bytes)?;
        let values = decode_values(payload).ok()?;
        let fits = values.len() == types.len()
            && values.iter().zip(types).all(|(v, t)| &v.port_type() == t);
        fits.then_some(values)
    }

    /// Stores a result.
    pub fn store(&self, key: &[u8; 32], values: &[Value]) -> std::io::Result<()> {
        let payload = encode_values(values);
        crate::image_io::write_atomic_with(&self.path(key), |w| {
            w.write_all(&ENTRY_MAGIC)?;
            w.write_all(blake3::hash(&payload).as_bytes())?;
            w.write_all(&payload)
        })
    }
}

/// First bytes of a cache entry (format 1: magic, 32-byte BLAKE3 of the payload, payload).
pub const ENTRY_MAGIC: [u8; 8] = *b"OCCACHE1";

/// The payload of a cache entry whose hash verifies.
fn verified_payload(bytes: &[u8]) -> Option<&[u8]> {
    let rest = bytes.strip_prefix(&ENTRY_MAGIC)?;
    let (hash, payload) = rest.split_at_checked(32)?;
    (blake3::hash(payload).as_bytes() == hash).then_some(payload)
}

/// BLAKE3 of some bytes (used by operators whose results depend on a file's contents).
pub fn content_hash(bytes: &[u8]) -> [u8; 32] {
    *blake3::hash(bytes).as_bytes()
}

/// An in-memory result cache shared by the runs of one animation (one run per frame), so a
/// node whose key does not change between frames is computed once.
///
/// Entries live for one *generation*: [`MemoryCache::end_generation`] (called after each
/// frame) drops every entry the frame did not store, load or touch (every node a run needs is
/// touched, cached or not), so a node whose parameters change every frame does not accumulate
/// one result per frame.
#[derive(Debug, Default)]
pub struct MemoryCache {
    inner: std::sync::Mutex<MemoryGenerations>,
}

#[derive(Debug, Default)]
struct MemoryGenerations {
    current: std::collections::HashMap<[u8; 32], std::sync::Arc<[Value]>>,
    previous: std::collections::HashMap<[u8; 32], std::sync::Arc<[Value]>>,
}

impl MemoryCache {
    /// An empty cache.
    pub fn new() -> MemoryCache {
        MemoryCache::default()
    }

    /// The stored result for `key`, if present and of the expected types; a hit keeps the
    /// entry alive for the next generation.
    pub fn load(&self, key: &[u8; 32], types: &[PortType]) -> Option<std::sync::Arc<[Value]>> {
        let mut inner = self.inner.lock().ok()?;
        let values = match inner.current.get(key) {
            Some(v) => v.clone(),
            None => {
                let v = inner.previous.remove(key)?;
                inner.current.insert(*key, v.clone());
                v
            }
        };
        let fits = values.len() == types.len()
            && values.iter().zip(types).all(|(v, t)| &v.port_type() == t);
        fits.then_some(values)
    }

    /// Keeps the entry for `key` (if any) alive for the next generation without reading it:
    /// a run touches the key of every node it needs, so the upstream of a cached node survives
    /// frames in which only the cached node itself was read.
    pub fn touch(&self, key: &[u8; 32]) {
        if let Ok(mut inner) = self.inner.lock()
            && let Some(v) = inner.previous.remove(key)
        {
            inner.current.insert(*key, v);
        }
    }

    /// Stores a result in the current generation.
    pub fn store(&self, key: &[u8; 32], values: std::sync::Arc<[Value]>) {
        if let Ok(mut inner) = self.inner.lock() {
            inner.current.insert(*key, values);
        }
    }

    /// Ends a generation: entries neither stored nor loaded since the last call are dropped.
    pub fn end_generation(&self) {
        if let Ok(mut inner) = self.inner.lock() {
            inner.previous = std::mem::take(&mut inner.current);
        }
    }

    /// Entries held (both generations).
    pub fn len(&self) -> usize {
        self.inner
            .lock()
            .map_or(0, |i| i.current.len() + i.previous.len())
    }

    /// Whether no entry is held.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn entries_whose_bytes_changed_are_not_loaded() {
        let dir = std::env::temp_dir().join(format!("ocellus-cache-test-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let cache = DiskCache::open(&dir).unwrap();
        let key = content_hash(b"node");
        let values = vec![Value::Scalar(0.25), Value::Integer(7)];
        let types: Vec<PortType> = values.iter().map(Value::port_type).collect();
        cache.store(&key, &values).unwrap();
        assert_eq!(cache.load(&key, &types).unwrap(), values);

        let path = cache.path(&key);
        let good = std::fs::read(&path).unwrap();
        // Any single flipped bit anywhere — magic, hash or payload (a float's mantissa, which
        // the codec alone would accept) — and any truncation make the entry a miss.
        for i in 0..good.len() {
            let mut bad = good.clone();
            bad[i] ^= 0x10;
            std::fs::write(&path, &bad).unwrap();
            assert!(cache.load(&key, &types).is_none(), "byte {i} flipped");
        }
        for len in [0, 8, 40, good.len() - 1] {
            std::fs::write(&path, &good[..len]).unwrap();
            assert!(cache.load(&key, &types).is_none(), "truncated to {len}");
        }
        // A bare codec payload (the previous entry format) is a miss, not a misread.
        std::fs::write(&path, encode_values(&values)).unwrap();
        assert!(cache.load(&key, &types).is_none());
        // Storing again repairs it.
        cache.store(&key, &values).unwrap();
        assert_eq!(cache.load(&key, &types).unwrap(), values);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
