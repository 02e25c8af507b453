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
//! [`stream::StreamStrategy`]: a frame streamed on one clock (a DAQ board whose analog
//!   outputs drive the stage and whose inputs record the QPD and the stage's position monitor
//!   on the same clock); a step is a line, binned as soon as its samples are in while the
//!   stream goes on.
//!
//! [`for_raster`] picks the raster strategy a stage calls for; the stop rule is the engine's.

pub mod line;
pub mod point;
pub mod stream;

use super::error::ScanError;
use super::limits::SoftLimits;
use super::plan::{Plan, Point};
use super::raster::{plan_lines, LineBins, RasterOptions, RasterPlan};
use crate::instrument::line::LineTiming;
use crate::instrument::{DeviceError, Instrument, Pos};
use ndarray::Array2;
use serde_json::{json, Value};

pub use line::LineStrategy;
pub use point::PointStrategy;
pub use stream::StreamStrategy;

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

/// What the engine's pre-flight hands [`Strategy::prepare`]: the plan, the start (the commanded
/// target), and every pixel (`points`, in visiting order) checked against `limits` (the soft
/// limits already narrowed to the travel range).
pub struct Checked<'a> {
    pub plan: &'a Plan,
    pub start: Pos,
    pub points: &'a [Point],
    pub limits: &'a SoftLimits,
}

impl Checked<'_> {
    /// The raster lines of the plan ([`plan_lines`]) for a stage of this `timing` that settles
    /// `settle_s` after each line's start; a refusal in the user's words.
    pub fn raster_lines(
        &self,
        timing: &LineTiming,
        settle_s: f64,
    ) -> Result<RasterPlan, ScanError> {
        plan_lines(self.plan, self.start, timing, settle_s, self.limits).map_err(ScanError::Refused)
    }
}

/// What one step of a scan gives: its pixels, or why it failed.
pub type StepResult = Result<Vec<Pixel>, StepFault>;

/// One acquisition mode. See the module documentation.
pub trait Strategy {
    /// `"points"` or `"raster"` (the scan's `meta.mode`).
    fn mode(&self) -> &'static str;
    /// The strategy's own pre-flight and configuration, after the engine has checked every
    /// pixel of the plan (`checked`). Nothing moves. `Err`: the refusal in the user's words, or
    /// the device error that kept the strategy from asking what the devices can do.
    fn prepare(&mut self, inst: &mut Instrument, checked: &Checked) -> Result<Layout, ScanError>;
    /// Acquire step `i` (0-based, in order; after a pause the next step re-arms whatever
    /// the pause stopped). Returns the step's pixels in the order measured.
    fn step(&mut self, inst: &mut Instrument, i: usize) -> StepResult;
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
    /// The pixels of the steps taken since the last call that had samples at or beyond the
    /// input's rail (`acquire::clip`); the engine asks after every step.
    fn take_clipped(&mut self) -> Vec<super::clip::ClippedPixel> {
        Vec::new()
    }
    /// Sz when the digitiser measured it: `false` blanks Sz to NaN.
    fn sz_measured(&self) -> bool {
        true
    }
}

pub use crate::instrument::samples_per_point;

/// The strategy of `mode: "raster"` on `inst`: the frame stream when the stage has one
/// (the stage's `FrameStream` capability), hardware-timed lines otherwise.
pub fn for_raster(inst: &mut Instrument, opts: RasterOptions) -> Box<dyn Strategy> {
    if inst.stage.frame_stream().is_some() {
        Box::new(StreamStrategy::new(opts))
    } else {
        Box::new(LineStrategy::new(opts))
    }
}

/// What the binned lines of a raster add up to, for `meta.raster`.
#[derive(Debug, Clone)]
pub struct BinStats {
    err_max: f64,
    err_ss: f64,
    n_err: usize,
    spp_min: usize,
    spp_sum: usize,
    lag_sum: f64,
    lag_n: usize,
    /// The digitiser's sample rate, Hz (the last line's).
    pub sample_rate: Option<f64>,
    /// Every line measured Sz.
    pub sz_measured: bool,
}

impl Default for BinStats {
    fn default() -> Self {
        BinStats {
            err_max: 0.0,
            err_ss: 0.0,
            n_err: 0,
            spp_min: usize::MAX,
            spp_sum: 0,
            lag_sum: 0.0,
            lag_n: 0,
            sample_rate: None,
            sz_measured: true,
        }
    }
}

impl BinStats {
    /// A line binned onto pixel centres `cols` (µm): samples per pixel and the distance of the
    /// samples' mean position from each centre.
    pub fn add_line(&mut self, bins: &LineBins, cols: &[f64]) {
        for (c, (&p, &n)) in bins.position.iter().zip(&bins.count).enumerate() {
            let e = p - cols[c];
            self.err_max = self.err_max.max(e.abs());
            self.err_ss += e * e;
            self.n_err += 1;
            self.spp_min = self.spp_min.min(n);
            self.spp_sum += n;
        }
    }

    /// The lag of a line: |target − measured| (µm) over the samples whose measured position
    /// lies among the pixels `cols`.
    pub fn add_lag(&mut self, target: &[f64], measured: &[f64], cols: &[f64]) {
        let (a, b) = (cols[0], cols[cols.len() - 1]);
        let (lo, hi) = (a.min(b), a.max(b));
        for (t, x) in target.iter().zip(measured) {
            if *x >= lo && *x <= hi {
                self.lag_sum += (t - x).abs();
                self.lag_n += 1;
            }
        }
    }

    /// The mean lag of the lines so far, µm (`None` before any sample among the pixels).
    pub fn lag_um_mean(&self) -> Option<f64> {
        (self.lag_n > 0).then(|| self.lag_sum / self.lag_n as f64)
    }

    /// Samples per pixel (min, mean), position error (max, rms, µm) and mean lag (µm) into
    /// the object `raster`.
    pub fn merge_into(&self, raster: &mut Value) {
        let n = self.n_err;
        raster["sample_rate_hz"] = json!(self.sample_rate);
        raster["samples_per_pixel_min"] =
            json!((self.spp_min != usize::MAX).then_some(self.spp_min));
        raster["samples_per_pixel_mean"] = json!((n > 0).then(|| self.spp_sum as f64 / n as f64));
        raster["position_error_um_max"] = json!((n > 0).then_some(self.err_max));
        raster["position_error_um_rms"] = json!((n > 0).then(|| (self.err_ss / n as f64).sqrt()));
        raster["lag_um_mean"] = json!((self.lag_n > 0).then(|| self.lag_sum / self.lag_n as f64));
        raster["sz_measured"] = json!(self.sz_measured);
    }
}

/// Rows × longest of `rows`, NaN-padded.
pub fn padded(rows: &[Vec<f64>], n_rows: usize) -> Array2<f64> {
    let w = rows.iter().map(Vec::len).max().unwrap_or(0);
    let mut a = Array2::from_elem((n_rows, w), f64::NAN);
    for (r, v) in rows.iter().enumerate() {
        for (k, &x) in v.iter().enumerate() {
            a[[r, k]] = x;
        }
    }
    a
}

/// The [`Strategy`] methods of the strategies that measure a raster line by line (`line`,
/// `stream`): a step is line `i` of the prepared plan (`self.rp`, measured by their
/// `line_step`), the stage rests where `self.at` says, and the clipped pixels wait in
/// `self.clipped`. Expanded inside their `impl Strategy`.
macro_rules! line_by_line_steps {
    () => {
        fn step(&mut self, inst: &mut Instrument, i: usize) -> StepResult {
            let rp = planned(&self.rp, inst)?;
            self.line_step(inst, &rp, i)
        }

        fn resting_at(&self) -> Option<Pos> {
            self.at
        }

        fn take_clipped(&mut self) -> Vec<crate::acquire::clip::ClippedPixel> {
            std::mem::take(&mut self.clipped)
        }
    };
}
pub(super) use line_by_line_steps;

/// The raster's plan, for a step: `prepare` made it (a step asked before is refused).
pub fn planned(
    rp: &Option<std::sync::Arc<super::raster::RasterPlan>>,
    inst: &mut Instrument,
) -> Result<std::sync::Arc<super::raster::RasterPlan>, StepFault> {
    rp.clone().ok_or_else(|| {
        StepFault::other(DeviceError::Other {
            device: inst.stage.name(),
            detail: "a raster line was asked before the raster was planned".into(),
        })
    })
}
