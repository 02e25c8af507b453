//! Where the fake vendor library `libfakebench.so` (tests/fakes/bench: Madlib + NI-DAQmx) is,
//! for integration tests of the bench drivers: `#[path = "support/fakebench.rs"] mod fakebench;`
//! then `fakebench::library()` for the path to put in the config's `library = ...` of both
//! backends (one file: dlopen of the same file twice is one instance, so the stage and the
//! board share their state).
//!
//! The library is a workspace member and a dev-dependency of bfpscope, so every `cargo test`
//! (also `cargo test --test NAME`) builds it before the tests run: a test build leaves it in
//! `target/<profile>/deps/`, `cargo build` in `target/<profile>/`; the newer of the two is
//! taken.

#![allow(dead_code)]

use std::path::PathBuf;

/// File name of the fake library on this platform.
pub const FILE: &str = "libfakebench.so";

/// Path of the built fake library; panics with what to do when it is not built.
pub fn library() -> PathBuf {
    let exe = std::env::current_exe().expect("the test executable's path");
    let deps = exe.parent().expect("the test executable's folder");
    let candidates = [
        deps.join(FILE),
        deps.parent().map(|p| p.join(FILE)).unwrap_or_default(),
    ];
    candidates
        .iter()
        .filter_map(|p| Some((std::fs::metadata(p).ok()?.modified().ok()?, p.clone())))
        .max()
        .map(|(_, p)| p)
        .unwrap_or_else(|| {
            panic!(
                "{FILE} not found in {} or its parent: build the workspace first (`cargo build` or \
                 `cargo test` at the repository root builds tests/fakes/bench)",
                deps.display()
            )
        })
}
