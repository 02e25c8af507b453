//! Test folders removed when the test process ends: `cleanup::at_exit(&dir)` (returns `dir`)
//! for every folder a test makes under the system's temporary folder, so that runs leave no
//! `bfpscope-*` folders behind. Set `BFPSCOPE_KEEP_TEST_DIRS=1` to keep them for a look after a
//! failure. Include with `#[path = "support/cleanup.rs"] mod cleanup;`.
//!
//! The removal runs from the C library's `atexit` (the test harness ends with `exit`, passed
//! or failed), once per process: a test cannot remove a folder another test of the same file
//! still uses.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::sync::{Mutex, Once};

static DIRS: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());
static HOOK: Once = Once::new();

extern "C" fn remove_all() {
    if std::env::var_os("BFPSCOPE_KEEP_TEST_DIRS").is_some() {
        return;
    }
    if let Ok(dirs) = DIRS.lock() {
        for d in dirs.iter() {
            let _ = std::fs::remove_dir_all(d);
        }
    }
}

/// Remove `dir` when the process ends; returns it.
pub fn at_exit(dir: &Path) -> PathBuf {
    HOOK.call_once(|| {
        // SAFETY: `atexit` with a function that takes nothing and unwinds nowhere (it only
        // removes folders, ignoring errors).
        unsafe {
            libc::atexit(remove_all);
        }
    });
    DIRS.lock()
        .unwrap_or_else(|e| e.into_inner())
        .push(dir.to_path_buf());
    dir.to_path_buf()
}
