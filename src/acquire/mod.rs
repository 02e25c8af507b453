//! The scan engine and every safety rule: plans (pure data), pre-flight against soft limits,
//! ETA, progress, pause, abort, return to start, partial data, autosave.
//!
//! Scripts describe (`plan`), one engine executes (`engine::run`) with an acquisition
//! strategy (`strategy`: point by point, hardware-timed lines) that only configures, acquires
//! one step and stops; drivers only move and read. No driver re-implements limits or abort.

pub mod clip;
pub mod engine;
pub mod error;
pub mod limits;
pub mod plan;
pub mod raster;
pub mod stop_rule;
pub mod store;
pub mod strategy;

pub use engine::{
    checked_move, run, run_plan, run_raster, Batcher, Ended, Paused, ScanEnv, ScanObserver,
    ScanRun, ScanStart,
};
pub use error::ScanError;
pub use limits::SoftLimits;
pub use plan::{Axis, Plan, Sweep};
pub use store::SessionStore;
