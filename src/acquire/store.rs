//! Where scans go: the session folder, through the data layer (`data::session::Session`,
//! `data::npz`): `scan_0001.npz`, `scan_0002.npz`, ... with increasing numbers, written to a
//! temporary name and hard-linked, so an existing file is never overwritten.
//!
//! The folder is created on the first save (a refused plan leaves no trace).

use crate::data::Scan;
use std::path::{Path, PathBuf};

/// File extension of autosaved scans.
pub const SCAN_EXT: &str = "npz";

/// The session folder.
#[derive(Debug, Clone)]
pub struct SessionStore {
    dir: PathBuf,
}

fn io_err(e: impl std::fmt::Display) -> std::io::Error {
    std::io::Error::other(e.to_string())
}

impl SessionStore {
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self { dir: dir.into() }
    }
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Highest scan number present in the folder (0 when none or no folder yet).
    pub fn last_number(&self) -> u32 {
        let Ok(rd) = std::fs::read_dir(&self.dir) else {
            return 0;
        };
        rd.filter_map(|e| e.ok())
            .filter_map(|e| crate::data::session::scan_number(&e.file_name().to_string_lossy()))
            .max()
            .unwrap_or(0) as u32
    }

    /// The path the next scan would get (`DIR/scan_0007.npz`), without reserving it.
    pub fn next_scan_path(&self) -> PathBuf {
        self.dir.join(scan_file_name(self.last_number() + 1))
    }

    /// Save `scan` under the next free number; never overwrites an existing file.
    pub fn autosave(&self, scan: &Scan) -> std::io::Result<PathBuf> {
        let session = crate::data::session::Session::open(&self.dir).map_err(io_err)?;
        session.autosave(scan).map_err(io_err)
    }
}

/// `scan_0042.npz`.
pub fn scan_file_name(n: u32) -> String {
    format!("scan_{n:04}.{SCAN_EXT}")
}

/// Save a scan to `path` (`.npz`, temporary name + rename). Refuses to overwrite an existing
/// file.
pub fn save_scan(path: &Path, scan: &Scan) -> std::io::Result<()> {
    if path.exists() {
        return Err(std::io::Error::new(
            std::io::ErrorKind::AlreadyExists,
            format!("{} exists; scans are never overwritten", path.display()),
        ));
    }
    if let Some(d) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(d)?;
    }
    crate::data::npz::save_scan(path, scan).map_err(io_err)
}

/// Load a scan written by [`save_scan`] / [`SessionStore::autosave`] (unmeasured pixels are
/// NaN).
pub fn load_scan(path: &Path) -> std::io::Result<Scan> {
    crate::data::npz::load_scan(path).map_err(io_err)
}
