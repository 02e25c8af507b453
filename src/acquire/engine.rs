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
use super::strategy::{for_raster, PointStrategy, StopCause, Strategy};
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

/// Run `plan` on `inst`, acquiring with `strategy`. See the module documentation.
pub fn run(
    inst: &mut Instrument,
    plan: &Plan,
    strategy: &mut dyn Strategy,
    env: &ScanEnv,
) -> Result<ScanRun, ScanError> {
    let kind = plan.kind.clone();
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
    let lay = strategy.prepare(inst, plan, start, &points, &limits)?;
    let mode = strategy.mode();
    let return_s = inst.settle_s + inst.stage.move_time_s();
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

    let (rows, cols) = (plan.rows(), plan.cols());
    let colv = plan.col_positions(start);
    let rowv = plan.row_positions(start);
    let (xn, yn) = (plan.fast.axis.name(), plan.row_axis().name());
    if let Some(o) = env.observer {
        o.started(&ScanStart {
            kind: &kind,
            rows,
            cols,
            x: &colv,
            y: &rowv,
            x_name: xn,
            y_name: yn,
            points_total: points.len(),
            eta_s: eta,
            meta: &env.meta,
        });
    }
    let mut img = [(); 3].map(|_| Array2::from_elem((rows, cols), f64::NAN));
    let mut clip = super::clip::ClipTally::new(rows, cols, inst.qpd.input_range());
    let clock = ScanClock::start(inst);
    let unit = lay.unit;
    let bar = progress_bar(env, lay.steps, &format!("{unit}s"), &kind);

    let mut ended = Ended::Complete;
    let mut measured = 0usize;
    let mut steps = 0usize;
    let mut batch = Batcher::new();
    // On a real-time instrument the ETA above is a floor (settle + dwell, and the move time
    // when the device knows it); after the first row the measured cost per step, link and
    // polling included, gives the real one.
    let revise_after = if inst.clock.is_virtual() || rows < 2 {
        usize::MAX
    } else {
        lay.steps_per_row
    };
    let mut measured_s_per_point: Option<f64> = None;
    // pauses (Ctrl-C answered "resume"): where and how long, wall time excluded from the
    // cost per step
    let mut pauses: Vec<Value> = vec![];
    let mut paused_wall = 0.0;
    let loop0 = std::time::Instant::now();
    for i in 0..lay.steps {
        if env.abort.swap(false, Ordering::SeqCst) {
            let Some(ask) = env.pause else {
                ended = Ended::Aborted { measured };
                break;
            };
            // a raster: the line is finished; the digitiser and the wave generator go off
            if let Err(error) = strategy.pause(inst) {
                ended = Ended::Failed {
                    measured,
                    error,
                    stage_fault: true,
                };
                break;
            }
            let t = std::time::Instant::now();
            let at = strategy.resting_at().unwrap_or(start);
            let info = Paused {
                kind: &kind,
                measured,
                total: points.len(),
                at,
            };
            if let Some(o) = env.observer {
                batch.flush(o);
                o.paused(true);
            }
            let resume = bar.suspend(|| ask(&info));
            if let Some(o) = env.observer {
                o.paused(false);
            }
            let dt = t.elapsed().as_secs_f64();
            paused_wall += dt;
            pauses.push(json!({
                "after_points": measured,
                "after_steps": steps,
                "at_um": at,
                "wall_s": dt,
                "resumed": resume,
            }));
            // a Ctrl-C pressed while the question was open counts as the answer
            if !resume || env.abort.swap(false, Ordering::SeqCst) {
                ended = Ended::Aborted { measured };
                break;
            }
            (env.log)(&format!(
                "{kind}: resumed at {unit} {} of {}",
                i + 1,
                lay.steps
            ));
        }
        let pixels = match strategy.step(inst, i) {
            Ok(p) => p,
            Err(f) => {
                ended = Ended::Failed {
                    measured,
                    error: f.error,
                    stage_fault: f.stage_fault,
                };
                break;
            }
        };
        for &(r, c, v) in &pixels {
            for (ch, x) in img.iter_mut().zip(v) {
                ch[[r, c]] = x;
            }
        }
        clip.add(&strategy.take_clipped());
        if let Some(o) = env.observer {
            if pixels.len() == 1 {
                batch.push(o, pixels[0]);
            } else {
                // a line at a time: a raster line is seconds of work at most
                batch.flush(o);
                o.points(&pixels);
            }
        }
        measured += pixels.len();
        steps += 1;
        bar.inc(1);
        if steps == revise_after {
            let wall = clock.wall_s() - paused_wall;
            measured_s_per_point = Some(wall / measured.max(1) as f64);
            let per = wall / steps as f64;
            if (per - lay.step_s).abs() > 0.1 * lay.step_s {
                (env.log)(&format!(
                    "{kind}: the first row took {} per {unit} (the ETA assumed {}): ETA now {} for the remaining {} {unit}s",
                    fmt_seconds(per),
                    fmt_seconds(lay.step_s),
                    fmt_seconds(per * (lay.steps - steps) as f64),
                    lay.steps - steps
                ));
            }
        }
    }
    let loop_s = loop0.elapsed().as_secs_f64() - paused_wall;
    bar.finish_and_clear();
    if let Some(o) = env.observer {
        batch.flush(o);
    }

    // the stop rule
    let stage_fault = matches!(
        ended,
        Ended::Failed {
            stage_fault: true,
            ..
        }
    );
    let mut stop = match &ended {
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
        let tail = if stage_fault {
            "; no further motion"
        } else {
            ""
        };
        (env.log)(&format!("{kind}: {note}{tail}"));
    }
    let stop_failed = matches!(stop, Some(Err(_)));
    let mut returned = false;
    let mut return_error = None;
    if plan.return_to_start && !stage_fault && !stop_failed {
        match inst.move_settle(start) {
            Ok(()) => returned = true,
            Err(e) => {
                (env.log)(&format!(
                    "{kind}: could NOT return to the start position: {e}"
                ));
                return_error = Some(e.to_string());
                // the one command the stage still gets is a stop
                let r = inst
                    .stage
                    .stop()
                    .map(|()| format!("stage stopped ({})", inst.stage.name()))
                    .map_err(|e| format!("the stop command failed too: {e}"));
                let (Ok(note) | Err(note)) = &r;
                (env.log)(&format!("{kind}: {note}"));
                stop = Some(r);
            }
        }
    }

    let status = ended.status();
    let mut meta = json!({
        "plan": plan,
        "mode": mode,
        "status": status,
        "points_total": points.len(),
        "points_measured": measured,
        "start_position_um": start,
        "returned_to_start": returned,
        "stop_sent": stop.is_some(),
        "stop": stop.as_ref().and_then(|r| r.as_ref().ok()),
        "stop_error": stop.as_ref().and_then(|r| r.as_ref().err()),
        "limits": limits,
        "instrument": inst.description,
        "time": clock.json(inst, eta),
    });
    meta["time"]["measured_s_per_point_first_row"] = json!(measured_s_per_point);
    meta["time"]["paused_wall_s"] = json!(paused_wall);
    if !pauses.is_empty() {
        meta["pauses"] = Value::Array(pauses);
    }
    if let Ended::Failed {
        error, stage_fault, ..
    } = &ended
    {
        meta["error"] = json!({ "message": error.to_string(), "stage_fault": stage_fault });
    }
    if let Some(e) = return_error {
        meta["return_error"] = json!(e);
    }
    let log_kind = |s: &str| (env.log)(&format!("{kind}: {s}"));
    if let Value::Object(extra) = strategy.metadata(inst, steps, loop_s, &log_kind) {
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
    let mk = |d: Array2<f64>| Image::new(d, colv.clone(), rowv.clone()).with_axis_names(xn, yn);
    let [sx, sy, mut sz] = img;
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

    // the QPD's metadata (the simulator's pipeline) and the script's (`env.meta`) merged into
    // the scan's, the autosave (a failure logged loudly), the live display told
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
    clip.finish(&mut scan, &kind, env.log);
    let saved = (env.save)(&scan);
    if let Err(e) = &saved {
        (env.log)(&format!(
            "WARNING: {kind}: autosave failed: {e}; save the scan by hand"
        ));
    }
    if let Some(o) = env.observer {
        o.ended(&scan, saved.as_ref().ok().map(|p| p.as_path()));
    }
    Ok(ScanRun {
        scan,
        saved,
        ended,
        returned_to_start: returned,
    })
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
