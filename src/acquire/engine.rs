//! The scan engine: executes a [`Plan`] on an [`Instrument`] with every safety rule in one
//! place.
//!
//! 1. Read the start position; pre-flight the whole plan against the soft limits (narrowed to
//!    the stage's travel range), the step-size rule and the speed limit (distance between
//!    consecutive points / (settle + dwell), see `limits`). A refused plan moves nothing.
//! 2. Print the ETA (settle + dwell per point, plus the move and QPD link times measured so
//!    far on hardware), show a progress bar when stderr is a terminal.
//! 3. Visit the points; before each one look at the abort flag (Ctrl-C): stop at the next point.
//! 4. Relative plans return to the start — after completion, after an abort and after a QPD
//!    error. After a **stage** error the stage is not commanded again (not even to return).
//! 5. Keep partial data (unmeasured pixels NaN) with status `aborted` / `failed`, attach the
//!    metadata and autosave — always, also after an abort or a device error. On a real-time
//!    instrument the metadata has `time.phases`: milliseconds per point spent moving, settling
//!    and reading the QPD, and per command what the links carried (printed as one line).

use super::limits::SoftLimits;
use super::plan::{fmt_seconds, Plan};
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
    /// paused between points — the stage at rest on the last point, nothing commanded — until
    /// it answers `true` (resume at the next point) or `false` (abort: the partial scan is kept
    /// and a relative scan returns to its start). Unset (scripts, tests): Ctrl-C aborts.
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
    /// The stage's commanded position (µm) where it waits: the last point measured, or the
    /// start before the first.
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

/// Nothing was measured: the plan was refused, or the start position could not be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ScanError {
    #[error("{0}")]
    Refused(String),
    #[error("{kind}: {error} (nothing was moved)")]
    Device { kind: String, error: DeviceError },
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

/// Send the stage its stop command after a fault (PI: `STP`), logging what happened; the error
/// text when the stop itself failed (e.g. the cable is gone).
fn stop_stage(inst: &mut Instrument, who: &str, env: &ScanEnv) -> Option<String> {
    match inst.stage.stop() {
        Ok(()) => {
            (env.log)(&format!("{who}: stage stopped ({})", inst.stage.name()));
            None
        }
        Err(e) => {
            (env.log)(&format!("{who}: the stop command failed too: {e}"));
            Some(e.to_string())
        }
    }
}

/// QPD samples per point for a dwell time: round(dwell · rate), at least 1.
pub fn samples_per_point(dwell_s: f64, rate_hz: f64) -> usize {
    ((dwell_s * rate_hz).round() as usize).max(1)
}

/// Run `plan` on `inst`. See the module documentation for the rules.
pub fn run_plan(inst: &mut Instrument, plan: &Plan, env: &ScanEnv) -> Result<ScanRun, ScanError> {
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

    let rate = inst.qpd.sample_rate();
    let n_samples = samples_per_point(plan.dwell_s, rate);
    let dwell_s = n_samples as f64 / rate;
    let speed = limits
        .check_speed(&kind, &points, inst.settle_s, dwell_s)
        .map_err(|e| ScanError::Refused(e.0))?;
    // the move time (the simulator's model, or the mean of the moves measured so far on
    // hardware, link included) and the QPD's measured time beyond its samples (link, reply)
    let move_s = inst.stage.move_time_s();
    let read_extra_s = inst.qpd.overhead_s();
    let eta = plan.eta_s(inst.settle_s + move_s + read_extra_s, dwell_s);
    let clock_kind = if inst.clock.is_virtual() {
        "simulated"
    } else {
        "real"
    };
    (env.log)(&format!(
        "{}: {} points, {}settle {} + dwell {}{} per point: ETA {} ({clock_kind} time)",
        plan.describe(),
        points.len(),
        if move_s > 0.0 {
            format!("move {} + ", fmt_seconds(move_s))
        } else {
            String::new()
        },
        fmt_seconds(inst.settle_s),
        fmt_seconds(n_samples as f64 / rate),
        if read_extra_s > 0.0 {
            format!(" + QPD link {}", fmt_seconds(read_extra_s))
        } else {
            String::new()
        },
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
    let mut sx = Array2::from_elem((rows, cols), f64::NAN);
    let mut sy = sx.clone();
    let mut sz = sx.clone();
    let clock = ScanClock::start(inst);
    let bar = progress_bar(env, points.len(), "points", &kind);

    let mut ended = Ended::Complete;
    let mut measured = 0usize;
    let mut batch = Batcher::new();
    // On a real-time instrument the ETA above is a floor (settle + dwell, and the move time
    // when the device knows it); after the first row the measured cost per point, link and
    // polling included, gives the real one.
    let per_point_eta = eta / points.len().max(1) as f64;
    let revise_after = if inst.clock.is_virtual() || rows < 2 {
        usize::MAX
    } else {
        cols
    };
    let mut measured_s_per_point: Option<f64> = None;
    // pauses (Ctrl-C answered "resume"): where and how long, wall time excluded from the
    // per-point cost
    let mut pauses: Vec<Value> = vec![];
    let mut paused_wall = 0.0;
    let mut at = start;
    // per-phase wall time of the points (real-time clocks), and the links' costs from here on
    let mut phases = Phases::default();
    let _ = (inst.stage.link_costs(), inst.qpd.link_costs());
    let loop0 = std::time::Instant::now();
    for p in &points {
        if env.abort.swap(false, Ordering::SeqCst) {
            let resume = env.pause.is_some_and(|ask| {
                let t = std::time::Instant::now();
                let info = Paused {
                    kind: &kind,
                    measured,
                    total: points.len(),
                    at,
                };
                let r = bar.suspend(|| ask(&info));
                let dt = t.elapsed().as_secs_f64();
                paused_wall += dt;
                pauses.push(
                    json!({"after_points": measured, "at_um": at, "wall_s": dt, "resumed": r}),
                );
                r
            });
            // a Ctrl-C pressed while the question was open counts as the answer
            if !resume || env.abort.swap(false, Ordering::SeqCst) {
                ended = Ended::Aborted { measured };
                break;
            }
            (env.log)(&format!(
                "{kind}: resumed at point {} of {}",
                measured + 1,
                points.len()
            ));
        }
        let t = std::time::Instant::now();
        let moved = inst.stage.move_to(p.target);
        phases.move_s += t.elapsed().as_secs_f64();
        if let Err(error) = moved {
            ended = Ended::Failed {
                measured,
                error,
                stage_fault: true,
            };
            break;
        }
        let t = std::time::Instant::now();
        inst.clock.wait(inst.settle_s);
        phases.settle_s += t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        // the scan stores the means only: the device may send less (SCPI: `MEAS:QPD?`)
        let read = inst.qpd.read_means(n_samples);
        phases.qpd_s += t.elapsed().as_secs_f64();
        match read {
            Ok(r) => {
                sx[[p.row, p.col]] = r.sx;
                sy[[p.row, p.col]] = r.sy;
                sz[[p.row, p.col]] = r.sz;
                at = p.target;
                if let Some(o) = env.observer {
                    batch.push(o, (p.row, p.col, [r.sx, r.sy, r.sz]));
                }
                measured += 1;
                if measured == revise_after {
                    let per = (clock.wall_s() - paused_wall) / measured as f64;
                    measured_s_per_point = Some(per);
                    if (per - per_point_eta).abs() > 0.1 * per_point_eta {
                        (env.log)(&format!(
                            "{kind}: the first row took {} per point (the ETA assumed {}): ETA now {} for the remaining {} points",
                            fmt_seconds(per),
                            fmt_seconds(per_point_eta),
                            fmt_seconds(per * (points.len() - measured) as f64),
                            points.len() - measured
                        ));
                    }
                }
                bar.inc(1);
            }
            Err(error) => {
                ended = Ended::Failed {
                    measured,
                    error,
                    stage_fault: false,
                };
                break;
            }
        }
    }
    phases.loop_s = loop0.elapsed().as_secs_f64() - paused_wall;
    phases.points = measured;
    phases.dwell_s = dwell_s;
    phases.stage_link = inst.stage.link_costs();
    phases.qpd_link = inst.qpd.link_costs();
    bar.finish_and_clear();
    if let Some(o) = env.observer {
        batch.flush(o);
    }
    let phases_json = (!inst.clock.is_virtual() && measured > 0).then(|| phases.to_json());
    if let Some(line) = phases_json.as_ref().and_then(|j| phase_summary(&kind, j)) {
        (env.log)(&line);
    }

    let stage_fault = matches!(
        ended,
        Ended::Failed {
            stage_fault: true,
            ..
        }
    );
    let mut returned = false;
    let mut return_error = None;
    if plan.return_to_start && !stage_fault {
        match inst.move_settle(start) {
            Ok(()) => returned = true,
            Err(e) => return_error = Some(e.to_string()),
        }
    }
    if let Some(e) = &return_error {
        (env.log)(&format!(
            "{kind}: could NOT return to the start position: {e}"
        ));
    }
    // After a stage fault (a controller error mid-move, an on-target timeout: the axis may
    // still be moving) or a failed return, the one command the stage still gets is a stop.
    let stop = (stage_fault || return_error.is_some()).then(|| stop_stage(inst, &kind, env));

    let status = ended.status();
    let mk = |d: Array2<f64>| Image::new(d, colv.clone(), rowv.clone()).with_axis_names(xn, yn);
    let mut meta = json!({
        "plan": plan,
        "status": status,
        "points_total": points.len(),
        "points_measured": measured,
        "samples_per_point": n_samples,
        "start_position_um": start,
        "returned_to_start": returned,
        "stop_sent": stop.is_some(),
        "stop_error": stop.clone().flatten(),
        "limits": limits,
        "max_speed_between_points_um_s": speed,
        "instrument": inst.description,
        "time": clock.json(inst, eta),
    });
    meta["time"]["measured_s_per_point_first_row"] = json!(measured_s_per_point);
    meta["time"]["paused_wall_s"] = json!(paused_wall);
    if !pauses.is_empty() {
        meta["pauses"] = Value::Array(pauses);
    }
    if let Some(j) = phases_json {
        meta["time"]["phases"] = j;
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
    let scan = Scan {
        sx: mk(sx),
        sy: mk(sy),
        sz: mk(sz),
        status,
        meta,
        raw: Vec::new(),
    };
    Ok(finish(inst, env, &kind, scan, ended, returned))
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

/// The end every scan shares (point by point and raster): the QPD's metadata (the simulator's
/// pipeline) and the script's (`env.meta`) merged into the scan's, the autosave (a failure
/// logged loudly), the live display told.
pub(crate) fn finish(
    inst: &Instrument,
    env: &ScanEnv,
    kind: &str,
    mut scan: Scan,
    ended: Ended,
    returned_to_start: bool,
) -> ScanRun {
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
        returned_to_start,
    }
}

/// Wall time of a scan's points by phase (real-time instruments), and what the links carried.
#[derive(Default)]
struct Phases {
    points: usize,
    /// The loop over the points, s.
    loop_s: f64,
    /// `move_to` (PI: `MOV`, `ERR?`, motion polling until on target), s, summed.
    move_s: f64,
    /// The settle wait, s, summed.
    settle_s: f64,
    /// QPD reads (command, acquisition, reply), s, summed.
    qpd_s: f64,
    /// Acquisition time per read, samples / rate, s.
    dwell_s: f64,
    stage_link: crate::instrument::link::LinkCosts,
    qpd_link: crate::instrument::link::LinkCosts,
}

impl Phases {
    /// `meta.time.phases`: milliseconds per point for each phase; per command word the count,
    /// bytes (both ways), write and reply milliseconds per point.
    fn to_json(&self) -> Value {
        let n = self.points.max(1) as f64;
        let ms = |s: f64| s / n * 1e3;
        let link = |costs: &crate::instrument::link::LinkCosts| {
            let mut m = serde_json::Map::new();
            for (w, c) in costs {
                m.insert(
                    w.clone(),
                    json!({
                        "per_point": c.n as f64 / n,
                        "bytes_per_point": (c.bytes_out + c.bytes_in) as f64 / n,
                        "write_ms": ms(c.write_s),
                        "reply_ms": ms(c.reply_s),
                    }),
                );
            }
            Value::Object(m)
        };
        let bytes: u64 = self
            .stage_link
            .iter()
            .chain(&self.qpd_link)
            .map(|(_, c)| c.bytes_out + c.bytes_in)
            .sum();
        let per_point = ms(self.loop_s);
        json!({
            "points": self.points,
            "per_point_ms": per_point,
            "move_ms": ms(self.move_s),
            "settle_ms": ms(self.settle_s),
            "qpd_ms": ms(self.qpd_s),
            "dwell_ms": self.dwell_s * 1e3,
            "qpd_beyond_dwell_ms": ms(self.qpd_s) - self.dwell_s * 1e3,
            "other_ms": per_point - ms(self.move_s + self.settle_s + self.qpd_s),
            "stage_link": link(&self.stage_link),
            "qpd_link": link(&self.qpd_link),
            "link_bytes_per_point": bytes as f64 / n,
        })
    }
}

/// One line for the operator from `meta.time.phases`: where the time per point went.
pub fn phase_summary(kind: &str, p: &Value) -> Option<String> {
    let f = |k: &str| p[k].as_f64();
    let cmds = |k: &str| -> String {
        p[k].as_object()
            .map(|m| {
                m.iter()
                    .map(|(w, c)| {
                        format!(
                            "{w} {:.2}× {:.2} ms",
                            c["per_point"].as_f64().unwrap_or(0.0),
                            c["write_ms"].as_f64().unwrap_or(0.0)
                                + c["reply_ms"].as_f64().unwrap_or(0.0)
                        )
                    })
                    .collect::<Vec<_>>()
                    .join(", ")
            })
            .unwrap_or_default()
    };
    Some(format!(
        "{kind}: {} points, {:.2} ms per point = move {:.2} ms [{}] + settle {:.2} ms + QPD {:.2} ms (dwell {:.2} ms) [{}] + other {:.2} ms; links {:.0} bytes per point",
        p["points"].as_u64()?,
        f("per_point_ms")?,
        f("move_ms")?,
        cmds("stage_link"),
        f("settle_ms")?,
        f("qpd_ms")?,
        f("dwell_ms")?,
        cmds("qpd_link"),
        f("other_ms")?,
        f("link_bytes_per_point")?,
    ))
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
