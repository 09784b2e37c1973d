//! The persistent result cache: one file per node result, named by the node's content key, so a
//! re-run after changing one parameter recomputes only what is downstream of it.
//!
//! Files are written atomically (temp file + rename), so concurrent runs sharing a folder and runs
//! killed mid-write never leave a torn entry; a corrupt or foreign file is ignored (recomputed).

use std::path::{Path, PathBuf};

use crate::codec::{decode_values, encode_values};
use crate::image_io::write_atomic;
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
        std::fs::create_dir_all(dir)?;
        Ok(DiskCache {
            dir: dir.to_path_buf(),
        })
    }

    /// The file holding a key's result.
    pub fn path(&self, key: &[u8; 32]) -> PathBuf {
        let hex: String = key.iter().map(|b| format!("{b:02x}")).collect();
        self.dir.join(format!("{hex}.ocv"))
    }

    /// The stored result for `key`, if present, readable and of the expected types.
    pub fn load(&self, key: &[u8; 32], types: &[PortType]) -> Option<Vec<Value>> {
        let bytes = std::fs::read(self.path(key)).ok()?;
        let values = decode_values(&bytes).ok()?;
        let fits = values.len() == types.len()
            && values.iter().zip(types).all(|(v, t)| &v.port_type() == t);
        fits.then_some(values)
    }

    /// Stores a result.
    pub fn store(&self, key: &[u8; 32], values: &[Value]) -> std::io::Result<()> {
        write_atomic(&self.path(key), &encode_values(values))
    }
}

/// BLAKE3 of some bytes (used by operators whose results depend on a file's contents).
pub fn content_hash(bytes: &[u8]) -> [u8; 32] {
    *blake3::hash(bytes).as_bytes()
}
