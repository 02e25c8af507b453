//! Acquisition strategies: how one step of a scan is measured. The engine
//! ([`super::engine::run`]) owns everything else — pre-flight of every pixel, ETA and its
//! revision, progress, pause/resume, abort, the return to start, autosave, metadata, the live
//! view — and drives a strategy that only configures (`prepare`), acquires one step (`step`:
//! a point, or a whole line) and stops (`pause`, `stop`).
//!
//! - [`point::PointStrategy`]: move, settle, read the QPD at every pixel; a step is a point.
//! - [`line::LineStrategy`]: hardware-timed lines (a stage with a wave generator and a data
//!   recorder, a digitiser started by the controller's trigger); a step is a line, binned by
//!   the measured position (`raster::bin_line`).
//!
//! A continuously streaming acquisition (a DAQ board whose analog output drives the stage and
//! whose inputs record the QPD and the stage's position monitor on the same clock) is a third
//! strategy of the same shape: `prepare` configures its tasks and checks its waveform, `step`
//! plays one row's output and bins that row's input by the measured position, `pause` and
//! `stop` stop the tasks. The stop rule is the engine's and needs nothing from it.

pub mod line;
pub mod point;

use super::engine::ScanError;
use super::limits::SoftLimits;
use super::plan::{Plan, Point};
use crate::instrument::{DeviceError, Instrument, Pos};
use ndarray::Array2;
use serde_json::Value;

pub use line::LineStrategy;
pub use point::PointStrategy;

/// A measured pixel: (row, column, [Sx, Sy, Sz]).
pub type Pixel = (usize, usize, [f64; 3]);

/// What a strategy will do, decided before the first move.
#[derive(Debug, Clone)]
pub struct Layout {
    /// Steps in all, and per image row (the ETA is revised after the first row).
    pub steps: usize,
    pub steps_per_row: usize,
    /// What a step is, singular: `"point"` or `"line"` (progress bar, messages).
    pub unit: &'static str,
    /// The estimated instrument time of one step, s.
    pub step_s: f64,
    /// How the ETA was made, for the operator (`"settle 5 ms + dwell 1 ms per point"`).
    pub eta_detail: String,
}

/// A step that failed: the device error, and whether it was the stage's (then the stage gets
/// no further command but a stop).
#[derive(Debug, Clone)]
pub struct StepFault {
    pub error: DeviceError,
    pub stage_fault: bool,
}

impl StepFault {
    pub fn stage(error: DeviceError) -> StepFault {
        StepFault {
            error,
            stage_fault: true,
        }
    }
    pub fn other(error: DeviceError) -> StepFault {
        StepFault {
            error,
            stage_fault: false,
        }
    }
}

/// Why a strategy is asked to stop.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StopCause {
    /// Ctrl-C answered "abort" (or a script's Ctrl-C).
    Abort,
    /// A device fault; `stage`: the stage's own.
    Fault { stage: bool },
}

/// One acquisition mode. See the module documentation.
pub trait Strategy {
    /// `"points"` or `"raster"` (the scan's `meta.mode`).
    fn mode(&self) -> &'static str;
    /// The strategy's own pre-flight and configuration, after the engine has checked every
    /// pixel (`points`, in visiting order) against `limits` (already narrowed to the travel
    /// range). Nothing moves. `Err`: the refusal in the user's words, or the device error
    /// that kept the strategy from asking what the devices can do.
    fn prepare(
        &mut self,
        inst: &mut Instrument,
        plan: &Plan,
        start: Pos,
        points: &[Point],
        limits: &SoftLimits,
    ) -> Result<Layout, ScanError>;
    /// Acquire step `i` (0-based, in order; after a pause the next step re-arms whatever
    /// the pause stopped). Returns the step's pixels in the order measured.
    fn step(&mut self, inst: &mut Instrument, i: usize) -> Result<Vec<Pixel>, StepFault>;
    /// The commanded stage position after the last step, if one was measured (µm).
    fn resting_at(&self) -> Option<Pos>;
    /// Ctrl-C between steps: bring the acquisition to rest for the pause (a line: the
    /// digitiser stopped, the wave generator off, the stage held where the line ended).
    /// Nothing moves. `Err`: the stop failed (the scan then ends as a stage fault).
    fn pause(&mut self, inst: &mut Instrument) -> Result<(), DeviceError>;
    /// The scan ends early: send the stop commands this mode needs for `cause` (after a
    /// stage fault at least the stage's stop). `None`: nothing needed stopping; `Some(Ok)`:
    /// what was stopped; `Some(Err)`: the stop failed too (the device's words).
    fn stop(&mut self, inst: &mut Instrument, cause: StopCause) -> Option<Result<String, String>>;
    /// The mode's own metadata, merged into the scan's (`meta.raster`, `meta.time.phases`,
    /// …), after the last step; `steps`: the steps measured, `loop_s`: the wall time of the
    /// loop over them (pauses excluded). `time` is merged key by key into the engine's.
    /// `log` tells the operator (where the time went).
    fn metadata(
        &mut self,
        inst: &mut Instrument,
        steps: usize,
        loop_s: f64,
        log: &dyn Fn(&str),
    ) -> Value;
    /// Raw arrays the scan file keeps beside the images (`Scan::raw`), rows × samples.
    fn raw(&mut self) -> Vec<(String, Array2<f64>)> {
        Vec::new()
    }
    /// Sz when the digitiser measured it: `false` blanks Sz to NaN.
    fn sz_measured(&self) -> bool {
        true
    }
}

/// QPD samples per point for a dwell time: round(dwell · rate), at least 1.
pub fn samples_per_point(dwell_s: f64, rate_hz: f64) -> usize {
    ((dwell_s * rate_hz).round() as usize).max(1)
}
