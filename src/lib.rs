//! bfpscope: back-focal-plane (BFP) interferometric microscopy workbench.
//!
//! Layout (see `docs/guide.md`): `optics` is the physics (pure functions), `instrument` the
//! device traits with the simulated and serial backends, `acquire` the scan engine and every
//! safety rule, `data` scans/images/files, `analysis` the quantitative steps of the paper,
//! `config` the one parse of `bfpscope.toml` and connecting what it names, `plot` figures,
//! `accuracy` the accuracy-vs-time knobs and their report, `view` the live web page, `script`
//! the Rhai engine and binding registry, `repl` the interactive prompt.

// Index loops over small fixed channel arrays read more clearly than iterator chains in numeric code.
#![allow(clippy::needless_range_loop)]

pub mod accuracy;
pub mod acquire;
pub mod analysis;
pub mod config;
pub mod data;
pub mod instrument;
pub mod optics;
pub mod plot;
pub mod repl;
pub mod script;
pub mod view;

/// Keep a long session's memory flat: glibc raises its mmap threshold after the first large
/// free (up to 32 MiB), after which every scan's large temporaries (render grids, arrays) come
/// from the main heap, where the small long-lived allocations of each scan (list rows,
/// metadata) pin them and the heap grows with the number of scans. A fixed 64 KiB threshold
/// returns large temporaries to the system at once. Measured by `cargo bench --features bench --bench view`
/// (process RSS after 100 and 300 scans). No-op off glibc.
pub fn tune_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        extern "C" {
            fn mallopt(param: i32, value: i32) -> i32;
        }
        const M_MMAP_THRESHOLD: i32 = -3;
        // SAFETY: mallopt only changes an allocator setting; called before any thread starts.
        unsafe {
            mallopt(M_MMAP_THRESHOLD, 64 * 1024);
        }
    }
}
