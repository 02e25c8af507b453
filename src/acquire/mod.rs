//! The scan engine and every safety rule: plans (pure data), pre-flight against soft limits,
//! ETA, progress, abort, return to start, partial data, autosave.
//!
//! Scripts describe (`plan`), the engine executes (`engine::run_plan`), drivers only move and
//! read. No driver re-implements limits or abort.

pub mod engine;
pub mod limits;
pub mod plan;
pub mod raster;
pub mod store;

pub use engine::{
    checked_move, run_plan, Batcher, Ended, Paused, ScanEnv, ScanError, ScanObserver, ScanRun,
    ScanStart,
};
pub use limits::SoftLimits;
pub use plan::{Axis, Plan, Sweep};
pub use store::SessionStore;
