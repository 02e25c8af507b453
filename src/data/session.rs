//! The session store: one folder per day (or the folder given with `--data DIR`) where every
//! scan is saved automatically as `scan_0001.npz`, `scan_0002.npz`, ...
//!
//! Rules (see `docs/files.md`):
//! - The next number is one more than the highest `scan_NNNN.npz` already in the folder; gaps are
//!   never filled, so numbers only increase within a folder.
//! - A file is never overwritten. [`Session::autosave`] writes the scan to a hidden temporary
//!   file, then links it to the final name with create-new semantics (`hard_link` fails if the
//!   name exists; the number is then increased and the link retried), so another process or
//!   thread saving at the same moment gets a different number, and a reader never sees a
//!   half-written `scan_NNNN.npz`.
//! - [`Session::next_scan_path`] reserves a name by creating it empty with `create_new`; the
//!   caller then writes it with [`save_scan`](super::save_scan), which renames over the
//!   placeholder.
//! - The default folder is `./bfpscope_data/YYYY-MM-DD/` with the UTC date.

use super::clock::utc_date;
use super::npz::write_scan_npz;
use super::{sync_file, sync_parent_dir, temp_path_for, DataError, Scan};
use std::fs::OpenOptions;
use std::io::ErrorKind;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

/// Root of the default session folders, relative to the working directory.
pub const DEFAULT_ROOT: &str = "bfpscope_data";

/// A session folder holding numbered scans.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Session {
    dir: PathBuf,
}

impl Session {
    /// Use `dir` as the session folder (created with its parents if missing).
    pub fn open(dir: impl Into<PathBuf>) -> Result<Session, DataError> {
        let dir = dir.into();
        if dir.as_os_str().is_empty() {
            return Err(DataError::invalid("data dir", "\"\"", "give a folder path"));
        }
        if dir.exists() && !dir.is_dir() {
            return Err(DataError::io(
                &dir,
                std::io::Error::new(ErrorKind::AlreadyExists, "exists and is not a folder"),
            ));
        }
        std::fs::create_dir_all(&dir).map_err(|e| DataError::io(&dir, e))?;
        Ok(Session { dir })
    }

    /// Check, without creating anything that stays, that scans can be saved in `dir`: it is a
    /// folder (or can be created: its nearest existing ancestor is a folder) and a file can be
    /// created in it (a probe file, removed at once). The error says what is wrong in words.
    pub fn check_writable(dir: &Path) -> Result<(), String> {
        if dir.as_os_str().is_empty() {
            return Err("the session folder is \"\": give a folder path".into());
        }
        let mut probe_dir = dir.to_path_buf();
        while !probe_dir.exists() {
            match probe_dir.parent() {
                Some(p) if !p.as_os_str().is_empty() => probe_dir = p.to_path_buf(),
                _ => {
                    probe_dir = PathBuf::from(".");
                    break;
                }
            }
        }
        if !probe_dir.is_dir() {
            return Err(if probe_dir == dir {
                format!(
                    "the session folder {} exists and is not a folder: scans could not be saved",
                    dir.display()
                )
            } else {
                format!(
                    "the session folder {} cannot be created: {} is not a folder",
                    dir.display(),
                    probe_dir.display()
                )
            });
        }
        let probe = probe_dir.join(format!(".bfpscope-write-check-{}", std::process::id()));
        match OpenOptions::new().write(true).create_new(true).open(&probe) {
            Ok(_) => {
                let _ = std::fs::remove_file(&probe);
                Ok(())
            }
            Err(e) if e.kind() == ErrorKind::AlreadyExists => Ok(()),
            Err(e) => Err(if probe_dir == dir {
                format!(
                    "the session folder {} is not writable ({e}): scans could not be saved",
                    dir.display()
                )
            } else {
                format!(
                    "the session folder {} cannot be created in {} ({e}): scans could not be saved",
                    dir.display(),
                    probe_dir.display()
                )
            }),
        }
    }

    /// The session for `--data DIR` if given, else today's folder under `./bfpscope_data/`.
    pub fn open_or_default(data_dir: Option<&Path>) -> Result<Session, DataError> {
        match data_dir {
            Some(d) => Session::open(d),
            None => Session::open(Session::default_dir(
                Path::new(DEFAULT_ROOT),
                SystemTime::now(),
            )),
        }
    }

    /// `root/YYYY-MM-DD` for the UTC date of `time`.
    pub fn default_dir(root: &Path, time: SystemTime) -> PathBuf {
        root.join(utc_date(time))
    }

    /// The session folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Numbered scan files in the folder, sorted by number.
    pub fn scan_files(&self) -> Result<Vec<(u64, PathBuf)>, DataError> {
        let rd = std::fs::read_dir(&self.dir).map_err(|e| DataError::io(&self.dir, e))?;
        let mut out = Vec::new();
        for entry in rd {
            let entry = entry.map_err(|e| DataError::io(&self.dir, e))?;
            if let Some(n) = entry.file_name().to_str().and_then(scan_number) {
                out.push((n, entry.path()));
            }
        }
        out.sort();
        Ok(out)
    }

    /// The highest-numbered scan file, if any.
    pub fn latest_scan_path(&self) -> Result<Option<PathBuf>, DataError> {
        Ok(self.scan_files()?.pop().map(|(_, p)| p))
    }

    fn next_number(&self) -> Result<u64, DataError> {
        Ok(self.scan_files()?.last().map_or(1, |(n, _)| n + 1))
    }

    /// Path of `scan_NNNN.npz` (at least four digits) in this folder.
    pub fn scan_path(&self, n: u64) -> PathBuf {
        self.dir.join(format!("scan_{n:04}.npz"))
    }

    /// Reserve the next scan name: the file is created empty with create-new semantics (so no
    /// other writer can take it) and its path returned. Write it with
    /// [`save_scan`](super::save_scan); a slot left empty reads back as a clear error.
    pub fn next_scan_path(&self) -> Result<PathBuf, DataError> {
        let mut n = self.next_number()?;
        for _ in 0..MAX_ATTEMPTS {
            let p = self.scan_path(n);
            match OpenOptions::new().write(true).create_new(true).open(&p) {
                Ok(_) => return Ok(p),
                Err(e) if e.kind() == ErrorKind::AlreadyExists => {
                    n = (n + 1).max(self.next_number()?);
                }
                Err(e) => return Err(DataError::io(&p, e)),
            }
        }
        Err(too_many_attempts(&self.dir))
    }

    /// Save `scan` under the next free number and return its path. Never overwrites: the data
    /// go to a temporary file first, which is then linked to the final name only if that name
    /// does not exist yet (retrying with the next number otherwise).
    pub fn autosave(&self, scan: &Scan) -> Result<PathBuf, DataError> {
        scan.check_consistent()?;
        let tmp = temp_path_for(&self.dir.join("scan.npz"));
        let result = write_scan_npz(&tmp, scan)
            .and_then(|()| sync_file(&tmp))
            .and_then(|()| self.link_to_next_number(&tmp));
        let _ = std::fs::remove_file(&tmp);
        if let Ok(p) = &result {
            sync_parent_dir(p);
        }
        result
    }

    fn link_to_next_number(&self, tmp: &Path) -> Result<PathBuf, DataError> {
        let mut n = self.next_number()?;
        for _ in 0..MAX_ATTEMPTS {
            let p = self.scan_path(n);
            match std::fs::hard_link(tmp, &p) {
                Ok(()) => return Ok(p),
                Err(e) if e.kind() == ErrorKind::AlreadyExists => {
                    n = (n + 1).max(self.next_number()?);
                }
                Err(_) => {
                    // File system without hard links: reserve the name, then rename over it.
                    let p = self.next_scan_path()?;
                    std::fs::rename(tmp, &p).map_err(|e| DataError::io(&p, e))?;
                    return Ok(p);
                }
            }
        }
        Err(too_many_attempts(&self.dir))
    }
}

const MAX_ATTEMPTS: usize = 100_000;

fn too_many_attempts(dir: &Path) -> DataError {
    DataError::io(
        dir,
        std::io::Error::other(format!("no free scan number after {MAX_ATTEMPTS} attempts")),
    )
}

/// The number of a scan file name `scan_<digits>.npz`, else `None`.
pub fn scan_number(file_name: &str) -> Option<u64> {
    let digits = file_name.strip_prefix("scan_")?.strip_suffix(".npz")?;
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    digits.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scan_numbers() {
        assert_eq!(scan_number("scan_0001.npz"), Some(1));
        assert_eq!(scan_number("scan_12345.npz"), Some(12345));
        assert_eq!(scan_number("scan_.npz"), None);
        assert_eq!(scan_number("scan_00a1.npz"), None);
        assert_eq!(scan_number("scan_0001.png"), None);
        assert_eq!(scan_number(".scan.tmp-1-2.npz"), None);
    }
}
