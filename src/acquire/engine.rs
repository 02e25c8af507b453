//! The scan engine: one loop executes a [`Plan`] on an [`Instrument`] with every safety rule
//! in one place, whatever the acquisition mode; an acquisition [`Strategy`] (point by point,
//! hardware-timed lines, …) only configures, acquires one step and stops.
//!
//! 1. Read the start position (the commanded target); pre-flight every pixel against the soft
//!    limits (narrowed to the stage's travel range) and the step-size rule, then the
//!    strategy's own checks (points: the speed between points; lines: the whole waveform and
//!    the line speed). A refused plan moves nothing.
//! 2. Print the ETA (the strategy's cost per step, plus the return of a relative scan), show a
//!    progress bar when stderr is a terminal; on a real-time instrument revise the ETA after
//!    the first row from its measured cost.
//! 3. Take the steps (a point; a line) in order. Before each one look at the abort flag
//!    (Ctrl-C). **The stop rule, every mode:**
//!    - Ctrl-C *pauses* between steps: point by point at the next point; a raster after the
//!      line being played (it is finished, the digitiser stopped, the wave generator off, the
//!      stage held where the line ended). The pause question (`ScanEnv::pause`) answers:
//!      resume (the next step re-arms and continues) or abort. Without a question (scripts,
//!      tests) Ctrl-C aborts.
//!    - Abort: a relative scan returns to its start; the partial scan is saved with status
//!      `aborted`.
//!    - A device fault: the strategy's stop commands (after a stage fault at least the stage's
//!      stop); after a **stage** fault nothing else is commanded to the stage (no return, no
//!      park move); after any other fault a relative scan returns to its start. The partial
//!      scan is saved with status `failed` and the device's words.
//! 4. Keep partial data (unmeasured pixels NaN), attach the metadata and autosave — always,
//!    also after an abort or a device error; tell the live view (`ScanObserver`).

use super::error::ScanError;
use super::limits::SoftLimits;
use super::plan::{fmt_seconds, Plan};
use super::raster::RasterOptions;
pub use super::strategy::samples_per_point;
use super::strategy::{for_raster, Checked, Layout, Pixel, PointStrategy, StopCause, Strategy};
use crate::data::clock::utc_now;
use crate::data::{Image, Scan, ScanStatus};
use crate::instrument::{DeviceError, Instrument, Pos};
use ndarray::Array2;
use serde_json::{json, Value};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};

/// What the engine needs besides the instrument and the plan.
pub struct ScanEnv<'a> {
    /// Soft limits from the config (narrowed to the travel range by the engine).
    pub limits: &'a SoftLimits,
    /// Set by Ctrl-C (or a test); the engine clears it when it acts on it.
    pub abort: &'a AtomicBool,
    /// Show an indicatif progress bar (callers pass `stderr().is_terminal()`).
    pub progress: bool,
    /// Messages for the operator (ETA, return to start, warnings).
    pub log: &'a dyn Fn(&str),
    /// Extra metadata merged into `scan.meta` (optics, scene, script path and hash, git...).
    pub meta: Value,
    /// Autosave: returns where the scan went.
    pub save: &'a dyn Fn(&Scan) -> Result<PathBuf, String>,
    /// A live display told of every point (the browser view), if any.
    pub observer: Option<&'a dyn ScanObserver>,
    /// Asked when Ctrl-C comes during the scan, if set (the prompt on a terminal): the scan is
    /// paused between steps — point by point at the next point, a raster after the line being
    /// played (digitiser stopped, wave generator off); the stage at rest, nothing commanded —
    /// until it answers `true` (resume with the next step) or `false` (abort: the partial scan
    /// is kept and a relative scan returns to its start). Unset (scripts, tests): Ctrl-C aborts.
    pub pause: Option<&'a dyn Fn(&Paused) -> bool>,
}

impl<'a> ScanEnv<'a> {
    /// An environment with no progress bar, no live display, no pause question (Ctrl-C aborts)
    /// and empty extra metadata: the accuracy report, tests and benches. Set other fields with
    /// struct update syntax (`ScanEnv { meta, ..ScanEnv::plain(…) }`).
    pub fn plain(
        limits: &'a SoftLimits,
        abort: &'a AtomicBool,
        log: &'a dyn Fn(&str),
        save: &'a dyn Fn(&Scan) -> Result<PathBuf, String>,
    ) -> Self {
        ScanEnv {
            limits,
            abort,
            progress: false,
            log,
            meta: json!({}),
            save,
            observer: None,
            pause: None,
        }
    }
}

/// Where a scan stands when Ctrl-C pauses it (see [`ScanEnv::pause`]).
#[derive(Debug, Clone)]
pub struct Paused<'a> {
    pub kind: &'a str,
    /// Points measured so far, and in all.
    pub measured: usize,
    pub total: usize,
    /// The stage's commanded position (µm) where it waits: the last point measured (a raster:
    /// where the last line's wave ended), or the start before the first.
    pub at: Pos,
}

/// What a live display (the browser view, `view/`) is told while a scan runs. Each call must
/// return at once (store and notify, never wait on a client): the engine makes them between
/// points, and a slow display must not slow a scan.
pub trait ScanObserver: Send + Sync {
    /// The scan starts: its grid (column and row positions, µm) and what it is.
    fn started(&self, start: &ScanStart);
    /// Points measured: each pixel (row, col) and its (Sx, Sy, Sz), in the order measured. The
    /// engine hands them over in batches (see [`Batcher`]), one at a time on a slow instrument.
    fn points(&self, pts: &[(usize, usize, [f64; 3])]);
    /// The scan ended (complete, aborted or failed) and was saved to `saved` (if it was).
    fn ended(&self, scan: &Scan, saved: Option<&std::path::Path>);
    /// Ctrl-C paused the scan (`true`, the pause question is open) or it resumes (`false`).
    fn paused(&self, _paused: bool) {}
}

/// Hands measured points to an observer in batches: one point per call while points come
/// slowly (hardware: the display follows every point), growing to [`Batcher::MAX`] while they
/// come fast (the simulator: one lock per batch, not per point, so the display costs the scan
/// next to nothing). The batch doubles while flushes come less than [`Batcher::FAST`] apart and
/// halves when they come more than [`Batcher::SLOW`] apart.
pub struct Batcher {
    pending: Vec<(usize, usize, [f64; 3])>,
    size: usize,
    last: std::time::Instant,
}

impl Batcher {
    pub const MAX: usize = 256;
    pub const FAST: std::time::Duration = std::time::Duration::from_millis(5);
    pub const SLOW: std::time::Duration = std::time::Duration::from_millis(50);

    pub fn new() -> Batcher {
        Batcher {
            pending: Vec::with_capacity(Self::MAX),
            size: 1,
            last: std::time::Instant::now(),
        }
    }

    /// Add a point; hand the batch over when it is full.
    pub fn push(&mut self, o: &dyn ScanObserver, p: (usize, usize, [f64; 3])) {
        self.pending.push(p);
        if self.pending.len() >= self.size {
            let dt = self.last.elapsed();
            self.flush(o);
            if dt < Self::FAST {
                self.size = (self.size * 2).min(Self::MAX);
            } else if dt > Self::SLOW {
                self.size = (self.size / 2).max(1);
            }
        }
    }

    /// Hand over what is pending.
    pub fn flush(&mut self, o: &dyn ScanObserver) {
        if !self.pending.is_empty() {
            o.points(&self.pending);
            self.pending.clear();
        }
        self.last = std::time::Instant::now();
    }
}

impl Default for Batcher {
    fn default() -> Self {
        Self::new()
    }
}

/// The header of a scan for a live display.
pub struct ScanStart<'a> {
    pub kind: &'a str,
    pub rows: usize,
    pub cols: usize,
    /// Column positions along the fast axis, µm.
    pub x: &'a [f64],
    /// Row positions along the slow axis, µm (one row for line and z scans).
    pub y: &'a [f64],
    pub x_name: &'a str,
    pub y_name: &'a str,
    pub points_total: usize,
    /// The engine's estimate of the instrument time, s.
    pub eta_s: f64,
    /// The script's metadata (protocol, notes, …) as it will be saved.
    pub meta: &'a Value,
}

/// How a scan ended.
#[derive(Debug, Clone, PartialEq)]
pub enum Ended {
    Complete,
    /// Ctrl-C after `measured` points.
    Aborted {
        measured: usize,
    },
    /// A device error after `measured` points. `stage_fault`: the stage itself failed and was
    /// not commanded again.
    Failed {
        measured: usize,
        error: DeviceError,
        stage_fault: bool,
    },
}

impl Ended {
    /// The status the scan file records.
    pub fn status(&self) -> ScanStatus {
        match self {
            Ended::Complete => ScanStatus::Complete,
            Ended::Aborted { .. } => ScanStatus::Aborted,
            Ended::Failed { .. } => ScanStatus::Failed,
        }
    }
}

/// A scan that ran (possibly partially): the data, where it was saved and how it ended.
#[derive(Debug, Clone)]
pub struct ScanRun {
    pub scan: Scan,
    pub saved: Result<PathBuf, String>,
    pub ended: Ended,
    pub returned_to_start: bool,
}

impl ScanRun {
    /// The outcome as a script sees it: `Ok` for a complete scan (the autosave path, or a
    /// warning when the autosave failed), `Err` with the whole story otherwise.
    pub fn summary(&self) -> Result<String, String> {
        let kind = self.scan.meta["plan"]["kind"]
            .as_str()
            .unwrap_or("scan")
            .to_string();
        let saved = match &self.saved {
            Ok(p) => format!("saved to {}", p.display()),
            Err(e) => format!("AUTOSAVE FAILED: {e}"),
        };
        let total = self.scan.meta["points_total"].as_u64().unwrap_or(0);
        let back = if self.returned_to_start {
            "; returned to start"
        } else {
            ""
        };
        match &self.ended {
            Ended::Complete => Ok(saved),
            Ended::Aborted { measured } => Err(format!(
                "{kind} aborted (Ctrl-C) after {measured} of {total} points{back}; partial scan (status aborted) {saved}"
            )),
            Ended::Failed { measured, error, stage_fault } => Err(format!(
                "{kind} failed after {measured} of {total} points: {error}{back}{}; partial scan (status failed) {saved}",
                if *stage_fault { "; the stage was not commanded further, but for a stop" } else { "" }
            )),
        }
    }
}

/// Run `plan` point by point on `inst` (move, settle, read at every pixel). See the module
/// documentation for the rules.
pub fn run_plan(inst: &mut Instrument, plan: &Plan, env: &ScanEnv) -> Result<ScanRun, ScanError> {
    run(inst, plan, &mut PointStrategy::new(), env)
}

/// Run `plan` on `inst`, acquiring with `strategy`. See the module documentation: the phases
/// below are its promises, in order — pre-flight, the steps (with the pause between them),
/// the stop, the return to the start, and the save.
pub fn run(
    inst: &mut Instrument,
    plan: &Plan,
    strategy: &mut dyn Strategy,
    env: &ScanEnv,
) -> Result<ScanRun, ScanError> {
    let pre = preflight(inst, plan, strategy, env)?;
    let steps = take_steps(inst, plan, strategy, env, &pre);
    let stop = stop(inst, strategy, env, &plan.kind, &steps.ended);
    let halt = return_to_start(inst, plan, env, pre.start, &steps.ended, stop);
    let ended = steps.ended.clone();
    let scan = record(inst, plan, strategy, env, pre, steps, &halt);
    Ok(save(env, &plan.kind, scan, ended, halt.returned))
}

/// What pre-flight established before anything moved: where the scan starts, the limits it
/// was checked against, the strategy's layout, the ETA and the image grid.
struct Preflight {
    /// The commanded target when the scan started: a relative scan returns exactly there.
    start: Pos,
    limits: SoftLimits,
    points_total: usize,
    lay: Layout,
    mode: &'static str,
    /// The ETA printed, s (steps, plus the return of a relative scan).
    eta: f64,
    rows: usize,
    cols: usize,
    /// Column and row positions, µm, and the axes they lie along.
    colv: Vec<f64>,
    rowv: Vec<f64>,
    xn: &'static str,
    yn: &'static str,
}

/// Pre-flight: read the start (the commanded target), check every pixel against the soft
/// limits narrowed to the travel range, let the strategy check and prepare its own part, and
/// print the ETA. A refused plan moves nothing.
fn preflight(
    inst: &mut Instrument,
    plan: &Plan,
    strategy: &mut dyn Strategy,
    env: &ScanEnv,
) -> Result<Preflight, ScanError> {
    let kind = &plan.kind;
    let dev = |error| ScanError::Device {
        kind: kind.clone(),
        error,
    };
    // the start is the commanded target: a relative scan returns exactly there
    let start: Pos = inst.stage.target().map_err(dev)?;
    let travel = inst.stage.travel_range().map_err(dev)?;
    let limits = env
        .limits
        .within_travel(travel)
        .map_err(|e| ScanError::Refused(e.message))?;
    let points = limits
        .preflight(plan, start)
        .map_err(|e| ScanError::Refused(e.0))?;
    let checked = Checked {
        plan,
        start,
        points: &points,
        limits: &limits,
    };
    let lay = strategy.prepare(inst, &checked)?;
    let mode = strategy.mode();
    let return_s = inst.settle_s
        + points
            .last()
            .map_or(0.0, |p| inst.stage.move_time_for_s(p.target, start));
    let eta = lay.steps as f64 * lay.step_s + if plan.return_to_start { return_s } else { 0.0 };
    let clock_kind = if inst.clock.is_virtual() {
        "simulated"
    } else {
        "real"
    };
    (env.log)(&format!(
        "{}{}: {}: ETA {} ({clock_kind} time)",
        plan.describe(),
        if mode == "points" {
            String::new()
        } else {
            format!(" {mode}")
        },
        lay.eta_detail,
        fmt_seconds(eta)
    ));
    Ok(Preflight {
        start,
        limits,
        points_total: points.len(),
        lay,
        mode,
        eta,
        rows: plan.rows(),
        cols: plan.cols(),
        colv: plan.col_positions(start),
        rowv: plan.row_positions(start),
        xn: plan.fast.axis.name(),
        yn: plan.row_axis().name(),
    })
}

/// What the steps produced: the images (unmeasured pixels NaN), how the scan ended, and the
/// counts and times the metadata records.
struct Steps {
    img: [Array2<f64>; 3],
    ended: Ended,
    measured: usize,
    steps: usize,
    batch: Batcher,
    clock: ScanClock,
    /// On a real-time instrument: the measured cost per point over the first row, s.
    measured_s_per_point: Option<f64>,
    /// Pauses (Ctrl-C answered "resume"): where and how long.
    pauses: Vec<Value>,
    /// Wall time spent paused, excluded from the cost per step.
    paused_wall: f64,
    /// Wall time of the steps, pauses excluded.
    loop_s: f64,
    /// Clipped and dark samples per pixel.
    clip: super::clip::ClipTally,
}

impl Steps {
    /// Store a step's pixels and hand them to the live display.
    fn keep(&mut self, pixels: &[Pixel], observer: Option<&dyn ScanObserver>) {
        for &(r, c, v) in pixels {
            for (ch, x) in self.img.iter_mut().zip(v) {
                ch[[r, c]] = x;
            }
        }
        if let Some(o) = observer {
            if pixels.len() == 1 {
                self.batch.push(o, pixels[0]);
            } else {
                // a line at a time: a raster line is seconds of work at most
                self.batch.flush(o);
                o.points(pixels);
            }
        }
        self.measured += pixels.len();
        self.steps += 1;
    }
}

/// The steps: take them in order (a point; a line), looking at the abort flag (Ctrl-C) before
/// each one; tell the live display; revise the ETA after the first row on a real-time
/// instrument. Ends at the last step, at an abort or at a device fault (`Steps::ended`).
fn take_steps(
    inst: &mut Instrument,
    plan: &Plan,
    strategy: &mut dyn Strategy,
    env: &ScanEnv,
    pre: &Preflight,
) -> Steps {
    let kind = &plan.kind;
    if let Some(o) = env.observer {
        o.started(&ScanStart {
            kind,
            rows: pre.rows,
            cols: pre.cols,
            x: &pre.colv,
            y: &pre.rowv,
            x_name: pre.xn,
            y_name: pre.yn,
            points_total: pre.points_total,
            eta_s: pre.eta,
            meta: &env.meta,
        });
    }
    let mut s = Steps {
        img: [(); 3].map(|_| Array2::from_elem((pre.rows, pre.cols), f64::NAN)),
        ended: Ended::Complete,
        measured: 0,
        steps: 0,
        batch: Batcher::new(),
        clock: ScanClock::start(inst),
        measured_s_per_point: None,
        pauses: vec![],
        paused_wall: 0.0,
        loop_s: 0.0,
        clip: super::clip::ClipTally::new(pre.rows, pre.cols, inst.qpd.input_range()),
    };
    let lay = &pre.lay;
    let bar = progress_bar(env, lay.steps, &format!("{}s", lay.unit), kind);
    // On a real-time instrument the ETA above is a floor (settle + dwell, and the move time
    // when the device knows it); after the first row the measured cost per step, link and
    // polling included, gives the real one.
    let revise_after = if inst.clock.is_virtual() || pre.rows < 2 {
        usize::MAX
    } else {
        lay.steps_per_row
    };
    let loop0 = std::time::Instant::now();
    for i in 0..lay.steps {
        if env.abort.swap(false, Ordering::SeqCst) {
            if let Some(ended) = pause(inst, kind, strategy, env, pre, &mut s, &bar, i) {
                s.ended = ended;
                break;
            }
        }
        let pixels = match strategy.step(inst, i) {
            Ok(p) => p,
            Err(f) => {
                s.ended = Ended::Failed {
                    measured: s.measured,
                    error: f.error,
                    stage_fault: f.stage_fault,
                };
                break;
            }
        };
        s.keep(&pixels, env.observer);
        s.clip.add(&strategy.take_clipped());
        bar.inc(1);
        if s.steps == revise_after {
            let wall = s.clock.wall_s() - s.paused_wall;
            s.measured_s_per_point = Some(wall / s.measured.max(1) as f64);
            let per = wall / s.steps as f64;
            if (per - lay.step_s).abs() > 0.1 * lay.step_s {
                (env.log)(&format!(
                    "{kind}: the first row took {} per {} (the ETA assumed {}): ETA now {} for the remaining {} {}s",
                    fmt_seconds(per),
                    lay.unit,
                    fmt_seconds(lay.step_s),
                    fmt_seconds(per * (lay.steps - s.steps) as f64),
                    lay.steps - s.steps,
                    lay.unit
                ));
            }
        }
    }
    s.loop_s = loop0.elapsed().as_secs_f64() - s.paused_wall;
    bar.finish_and_clear();
    if let Some(o) = env.observer {
        s.batch.flush(o);
    }
    s
}

/// The pause: Ctrl-C came before step `i`. Without a pause question the scan aborts; with one
/// the strategy pauses (a raster: the line is finished, digitiser and wave generator off), the
/// question is asked with the stage at rest, and the answer resumes (`None`) or ends the scan
/// (`Some`: aborted; failed when the pause itself failed). A Ctrl-C pressed while the question
/// was open counts as the answer "abort".
#[allow(clippy::too_many_arguments)]
fn pause(
    inst: &mut Instrument,
    kind: &str,
    strategy: &mut dyn Strategy,
    env: &ScanEnv,
    pre: &Preflight,
    s: &mut Steps,
    bar: &indicatif::ProgressBar,
    i: usize,
) -> Option<Ended> {
    let measured = s.measured;
    let Some(ask) = env.pause else {
        return Some(Ended::Aborted { measured });
    };
    // a raster: the line is finished; the digitiser and the wave generator go off
    if let Err(error) = strategy.pause(inst) {
        return Some(Ended::Failed {
            measured,
            error,
            stage_fault: true,
        });
    }
    let t = std::time::Instant::now();
    let at = strategy.resting_at().unwrap_or(pre.start);
    let info = Paused {
        kind,
        measured,
        total: pre.points_total,
        at,
    };
    if let Some(o) = env.observer {
        s.batch.flush(o);
        o.paused(true);
    }
    let resume = bar.suspend(|| ask(&info));
    if let Some(o) = env.observer {
        o.paused(false);
    }
    let dt = t.elapsed().as_secs_f64();
    s.paused_wall += dt;
    s.pauses.push(json!({
        "after_points": measured,
        "after_steps": s.steps,
        "at_um": at,
        "wall_s": dt,
        "resumed": resume,
    }));
    // a Ctrl-C pressed while the question was open counts as the answer
    if !resume || env.abort.swap(false, Ordering::SeqCst) {
        return Some(Ended::Aborted { measured });
    }
    (env.log)(&format!(
        "{kind}: resumed at {} {} of {}",
        pre.lay.unit,
        i + 1,
        pre.lay.steps
    ));
    None
}

/// The stop: after an abort or a fault the strategy's stop commands (after a stage fault at
/// least the stage's stop), logged with what they did. `None` after a complete scan (nothing
/// sent); `Some(Err)` when a stop command failed.
fn stop(
    inst: &mut Instrument,
    strategy: &mut dyn Strategy,
    env: &ScanEnv,
    kind: &str,
    ended: &Ended,
) -> Option<Result<String, String>> {
    let stop = match ended {
        Ended::Complete => None,
        Ended::Aborted { .. } => strategy.stop(inst, StopCause::Abort),
        Ended::Failed { stage_fault, .. } => strategy.stop(
            inst,
            StopCause::Fault {
                stage: *stage_fault,
            },
        ),
    };
    if let Some(r) = &stop {
        let (Ok(note) | Err(note)) = r;
        let tail = if is_stage_fault(ended) {
            "; no further motion"
        } else {
            ""
        };
        (env.log)(&format!("{kind}: {note}{tail}"));
    }
    stop
}

/// A stage fault: after it nothing but a stop is commanded to the stage.
fn is_stage_fault(ended: &Ended) -> bool {
    matches!(
        ended,
        Ended::Failed {
            stage_fault: true,
            ..
        }
    )
}

/// How the scan was brought to rest: the stop sent (if any; the stage's own stop when the
/// return failed) and the return to the start.
struct Halt {
    stop: Option<Result<String, String>>,
    returned: bool,
    return_error: Option<String>,
}

/// The return: a relative scan goes back to its start — unless the stage faulted or a stop
/// command failed. If the return itself fails, the one command the stage still gets is a stop.
fn return_to_start(
    inst: &mut Instrument,
    plan: &Plan,
    env: &ScanEnv,
    start: Pos,
    ended: &Ended,
    stop: Option<Result<String, String>>,
) -> Halt {
    let kind = &plan.kind;
    let mut halt = Halt {
        stop,
        returned: false,
        return_error: None,
    };
    let stop_failed = matches!(halt.stop, Some(Err(_)));
    if !plan.return_to_start || is_stage_fault(ended) || stop_failed {
        return halt;
    }
    match inst.move_settle(start) {
        Ok(()) => halt.returned = true,
        Err(e) => {
            (env.log)(&format!(
                "{kind}: could NOT return to the start position: {e}"
            ));
            halt.return_error = Some(e.to_string());
            // the one command the stage still gets is a stop
            let r = inst
                .stage
                .stop()
                .map(|()| format!("stage stopped ({})", inst.stage.name()))
                .map_err(|e| format!("the stop command failed too: {e}"));
            let (Ok(note) | Err(note)) = &r;
            (env.log)(&format!("{kind}: {note}"));
            halt.stop = Some(r);
        }
    }
    halt
}

/// The scan as it will be saved: the partial data (unmeasured pixels NaN), the engine's
/// metadata (plan, status, counts, stop and return, limits, instrument, times), the strategy's,
/// the QPD's (the simulator's pipeline) and the script's (`env.meta`) merged in that order.
fn record(
    inst: &mut Instrument,
    plan: &Plan,
    strategy: &mut dyn Strategy,
    env: &ScanEnv,
    pre: Preflight,
    s: Steps,
    halt: &Halt,
) -> Scan {
    let kind = &plan.kind;
    let status = s.ended.status();
    let stop = &halt.stop;
    let mut meta = json!({
        "plan": plan,
        "mode": pre.mode,
        "status": status,
        "points_total": pre.points_total,
        "points_measured": s.measured,
        "start_position_um": pre.start,
        "returned_to_start": halt.returned,
        "stop_sent": stop.is_some(),
        "stop": stop.as_ref().and_then(|r| r.as_ref().ok()),
        "stop_error": stop.as_ref().and_then(|r| r.as_ref().err()),
        "limits": pre.limits,
        "instrument": inst.description,
        "time": s.clock.json(inst, pre.eta),
    });
    meta["time"]["measured_s_per_point_first_row"] = json!(s.measured_s_per_point);
    meta["time"]["paused_wall_s"] = json!(s.paused_wall);
    if !s.pauses.is_empty() {
        meta["pauses"] = Value::Array(s.pauses);
    }
    if let Ended::Failed {
        error, stage_fault, ..
    } = &s.ended
    {
        meta["error"] = json!({ "message": error.to_string(), "stage_fault": stage_fault });
    }
    if let Some(e) = &halt.return_error {
        meta["return_error"] = json!(e);
    }
    let log_kind = |m: &str| (env.log)(&format!("{kind}: {m}"));
    if let Value::Object(extra) = strategy.metadata(inst, s.steps, s.loop_s, &log_kind) {
        for (k, v) in extra {
            match (k.as_str(), v) {
                ("time", Value::Object(t)) => {
                    for (tk, tv) in t {
                        meta["time"][tk.as_str()] = tv;
                    }
                }
                (_, v) => meta[k.as_str()] = v,
            }
        }
    }
    let mk = |d: Array2<f64>| {
        Image::new(d, pre.colv.clone(), pre.rowv.clone()).with_axis_names(pre.xn, pre.yn)
    };
    let s_clip = s.clip;
    let [sx, sy, mut sz] = s.img;
    if !strategy.sz_measured() {
        sz.fill(f64::NAN);
    }
    let mut scan = Scan {
        sx: mk(sx),
        sy: mk(sy),
        sz: mk(sz),
        status,
        meta,
        raw: strategy.raw(),
        flags: Default::default(),
    };
    if let Some(Value::Object(q)) = inst.qpd.metadata() {
        for (k, v) in q {
            scan.meta[k.as_str()] = v;
        }
    }
    if let (Value::Object(m), Value::Object(extra)) = (&mut scan.meta, &env.meta) {
        for (k, v) in extra {
            m.insert(k.clone(), v.clone());
        }
    }
    // clipped and dark pixels: in the scan, its metadata, and said to the operator
    s_clip.finish(&mut scan, kind, env.log);
    scan
}

/// The save: always, also after an abort or a device error (a failure logged loudly); then the
/// live display is told.
fn save(env: &ScanEnv, kind: &str, scan: Scan, ended: Ended, returned: bool) -> ScanRun {
    let saved = (env.save)(&scan);
    if let Err(e) = &saved {
        (env.log)(&format!(
            "WARNING: {kind}: autosave failed: {e}; save the scan by hand"
        ));
    }
    if let Some(o) = env.observer {
        o.ended(&scan, saved.as_ref().ok().map(|p| p.as_path()));
    }
    ScanRun {
        scan,
        saved,
        ended,
        returned_to_start: returned,
    }
}

/// When a scan started, on the wall and on the instrument's clock.
pub(crate) struct ScanClock {
    wall0: std::time::Instant,
    wall_start: String,
    t0: f64,
}

impl ScanClock {
    pub(crate) fn start(inst: &Instrument) -> Self {
        ScanClock {
            wall0: std::time::Instant::now(),
            wall_start: utc_now(),
            t0: inst.clock.now(),
        }
    }

    /// Wall seconds since the start.
    pub(crate) fn wall_s(&self) -> f64 {
        self.wall0.elapsed().as_secs_f64()
    }

    /// The `time` block every scan records (wall and instrument time, the ETA); each engine
    /// adds its own keys.
    pub(crate) fn json(&self, inst: &Instrument, eta_s: f64) -> Value {
        let t1 = inst.clock.now();
        json!({
            "wall_start": self.wall_start,
            "wall_end": utc_now(),
            "wall_s": self.wall_s(),
            "clock": if inst.clock.is_virtual() { "virtual" } else { "wall" },
            "instrument_start_s": self.t0,
            "instrument_end_s": t1,
            "instrument_s": t1 - self.t0,
            "eta_s": eta_s,
        })
    }
}

/// A progress bar over `len` `unit`s when the environment asks for one (a terminal), hidden
/// otherwise.
pub(crate) fn progress_bar(
    env: &ScanEnv,
    len: usize,
    unit: &str,
    kind: &str,
) -> indicatif::ProgressBar {
    if !env.progress {
        return indicatif::ProgressBar::hidden();
    }
    let b = indicatif::ProgressBar::new(len as u64);
    if let Ok(style) = indicatif::ProgressStyle::with_template(&format!(
        "{{msg}} [{{bar:40}}] {{pos}}/{{len}} {unit}, ETA {{eta}}"
    )) {
        b.set_style(style.progress_chars("=> "));
    }
    b.set_message(kind.to_string());
    b
}

/// Move to an absolute target after checking it against the soft limits (narrowed to the
/// travel range). `who` names the binding for the message. Ctrl-C (`abort`) during the wait for
/// on-target stops the stage (PI: `STP`) and fails the call; the flag stays raised, so the
/// script is interrupted too.
pub fn checked_move(
    inst: &mut Instrument,
    limits: &SoftLimits,
    target: Pos,
    who: &str,
    abort: &AtomicBool,
) -> Result<(), String> {
    let travel = inst
        .stage
        .travel_range()
        .map_err(|e| format!("{who}: {e}"))?;
    limits
        .within_travel(travel)
        .map_err(|e| format!("{who} refused, nothing was moved: {e}"))?
        .check(target)
        .map_err(|e| format!("{who} refused, nothing was moved: {e}"))?;
    let stop = |inst: &mut Instrument| match inst.stage.stop() {
        Ok(()) => "the stage was stopped".to_string(),
        Err(s) => format!("the stop command failed too: {s}"),
    };
    match inst.stage.move_to_or_abort(target, abort) {
        Ok(true) => {
            inst.clock.wait(inst.settle_s);
            Ok(())
        }
        Ok(false) => Err(format!(
            "{who} interrupted (Ctrl-C) before {} was on target; {}",
            inst.stage.name(),
            stop(inst)
        )),
        // the axis may still be moving: stop it, and say whether that worked
        Err(e) => Err(format!("{who}: {e}; {}", stop(inst))),
    }
}

/// Run `plan` as a hardware-timed raster on `inst`: the engine's loop
/// ([`run`]) with the raster strategy the stage calls for
/// ([`super::strategy::for_raster`]: hardware-timed lines, or a streamed frame).
pub fn run_raster(
    inst: &mut Instrument,
    plan: &Plan,
    opts: &RasterOptions,
    env: &ScanEnv,
) -> Result<ScanRun, ScanError> {
    let mut s = for_raster(inst, *opts);
    run(inst, plan, s.as_mut(), env)
}
