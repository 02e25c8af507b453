//! Where the fake vendor library `libfakebench.so` (tests/fakes/bench: Madlib + NI-DAQmx) is,
//! for integration tests of the bench drivers: `fakebench::library()` gives the path to put in
//! the config's `library = ...` of both backends (one file: dlopen of the same file twice is one
//! instance, so the stage and the board share their state).
//!
//! The library is a workspace default member, so the README's `cargo test` (and `cargo build`)
//! at the repository root builds it before any test runs: a test build leaves it in
//! `target/<profile>/deps/`, `cargo build` in `target/<profile>/`; the newer of the two is
//! taken. It is deliberately not a dev-dependency of bfpscope: the fake links bfpscope's
//! simulator, so as a dev-dependency it made the library's unit-test build wait for the whole
//! library and the fake to be built first (about two minutes of CI's clean build).
//!
//! A run of a single test file (`cargo test --test NAME`) does not build the fake: when it is
//! missing, or older than its sources, `library()` stops with the command that builds it.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::time::SystemTime;

/// File name of the fake library on this platform.
pub const FILE: &str = "libfakebench.so";

/// The newest modification time of the fake's sources (its `src/` and `Cargo.toml`).
fn sources_modified() -> Option<SystemTime> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fakes/bench");
    let mut newest = std::fs::metadata(root.join("Cargo.toml"))
        .ok()?
        .modified()
        .ok()?;
    for entry in std::fs::read_dir(root.join("src")).ok()?.flatten() {
        if let Ok(t) = entry.metadata().and_then(|m| m.modified()) {
            newest = newest.max(t);
        }
    }
    Some(newest)
}

/// Path of the built fake library; panics with what to do when it is missing or stale. Found
/// and checked once per test process.
pub fn library() -> PathBuf {
    static FOUND: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    FOUND.get_or_init(find).clone()
}

fn find() -> PathBuf {
    let exe = std::env::current_exe().expect("the test executable's path");
    let deps = exe.parent().expect("the test executable's folder");
    let candidates = [
        deps.join(FILE),
        deps.parent().map(|p| p.join(FILE)).unwrap_or_default(),
    ];
    let (built, path) = candidates
        .iter()
        .filter_map(|p| Some((std::fs::metadata(p).ok()?.modified().ok()?, p.clone())))
        .max()
        .unwrap_or_else(|| {
            panic!(
                "{FILE} not found in {} or its parent: build it with `cargo build -p fakebench` \
                 (the README's `cargo test` at the repository root builds it too)",
                deps.display()
            )
        });
    if let Some(src) = sources_modified() {
        assert!(
            built >= src,
            "{} is older than tests/fakes/bench's sources: rebuild it with `cargo build -p \
             fakebench` (the README's `cargo test` at the repository root rebuilds it too)",
            path.display()
        );
    }
    path
}
