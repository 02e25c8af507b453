//! The stop rule of the one scan engine (`acquire::engine::run`), the same cases through every
//! acquisition mode (point by point, hardware-timed raster) on every backend that has both
//! (the simulator; the emulated PI GCS stage with its wave generator + the emulated Red Pitaya,
//! spoken to by the real drivers):
//!
//! 1. Ctrl-C, then resume: the scan pauses between steps (a point; a raster after the line
//!    being swept, the digitiser stopped and the wave generator off), resumes with the next
//!    step (a raster configured and armed again) and ends equal to an uninterrupted scan;
//! 2. Ctrl-C, then abort, of a relative scan: it returns to its start, the partial scan is
//!    saved with status `aborted`, the rows measured kept and the others NaN;
//! 3. a stage fault mid-scan: a stop command, no motion command after the fault (not even the
//!    return of a relative scan), the partial scan saved with status `failed`, the message
//!    naming the device and its reply.
//!
//! Ctrl-C and the simulator's stage fault are injected by a wrapper around the instrument's
//! stage (it counts the engine's calls, raises the Ctrl-C flag during the n-th move or line,
//! or fails the n-th call); the emulators' stage faults are the emulated controller's own
//! (a rejected `MOV`, a rejected `DRR?`), so the message is the driver's.

use crate::support::cleanup;

use bfpscope::acquire::raster::RasterOptions;
use bfpscope::acquire::store::{load_scan, SessionStore};
use bfpscope::acquire::strategy::{LineStrategy, PointStrategy, Strategy};
use bfpscope::acquire::{run, Axis, Ended, Paused, Plan, ScanEnv, ScanRun, SoftLimits, Sweep};
use bfpscope::config::connect::{connect_emulated_redpitaya, Emulated, EmulatedStageLink};
use bfpscope::config::Config;
use bfpscope::data::ScanStatus;
use bfpscope::instrument::line::{LineSweep, LineTiming, SweepRecord};
use bfpscope::instrument::link::LinkCosts;
use bfpscope::instrument::sim::scene::{Bead, Scene};
use bfpscope::instrument::sim::{SimConfig, SimCore};
use bfpscope::instrument::{
    Capability, CapabilityKind, DeviceError, Instrument, LineScan, Pos, Stage,
};
use bfpscope::optics::Optics;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

const NX: usize = 8;
const NY: usize = 4;
/// Where every scan starts (µm): off the origin, so that the return is seen.
const START: Pos = [0.2, -0.1, 0.0];

#[derive(Debug, Clone, Copy, PartialEq)]
enum Mode {
    Points,
    Raster,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Backend {
    Sim,
    Emulated,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Case {
    PauseResume,
    PauseAbort,
    StageFault,
}

impl Mode {
    /// The stage call during which Ctrl-C comes, and its count: the 11th point's move; the
    /// 2nd line's wave.
    fn ctrl_c_at(self) -> (&'static str, usize) {
        match self {
            Mode::Points => ("move_to", 11),
            Mode::Raster => ("start_line", 2),
        }
    }
    /// Pixels measured when the scan pauses (or the fault comes).
    fn measured_at_stop(self) -> usize {
        match self {
            Mode::Points => 11,
            Mode::Raster => 2 * NX,
        }
    }
    fn strategy(self) -> Box<dyn Strategy> {
        match self {
            Mode::Points => Box::new(PointStrategy::new()),
            Mode::Raster => Box::new(LineStrategy::new(RasterOptions::default())),
        }
    }
}

/// The stage calls the engine makes, in order.
type Calls = Arc<Mutex<Vec<&'static str>>>;

/// The instrument's stage, wrapped: every call is counted and logged; Ctrl-C (`abort`) is
/// raised during the `ctrl_c`-th call of its name; the `fail`-th call of its name fails as a
/// controller would (on the simulator, which has no faults of its own).
struct Tap {
    inner: Box<dyn Stage>,
    calls: Calls,
    abort: Arc<AtomicBool>,
    ctrl_c: Option<(&'static str, usize)>,
    fail: Option<(&'static str, usize)>,
}

impl Tap {
    fn call(&mut self, name: &'static str) -> Result<(), DeviceError> {
        let mut calls = self.calls.lock().unwrap();
        calls.push(name);
        let n = calls.iter().filter(|c| **c == name).count();
        if self.ctrl_c == Some((name, n)) {
            self.abort.store(true, Ordering::SeqCst);
        }
        if self.fail == Some((name, n)) {
            return Err(DeviceError::Controller {
                device: self.inner.name(),
                command: format!("({name} #{n})"),
                code: 7,
                message: "Position out of limits (injected)".into(),
            });
        }
        Ok(())
    }
}

impl Stage for Tap {
    fn name(&self) -> String {
        self.inner.name()
    }
    fn position(&mut self) -> Result<Pos, DeviceError> {
        self.inner.position()
    }
    fn target(&mut self) -> Result<Pos, DeviceError> {
        self.inner.target()
    }
    fn move_to(&mut self, target: Pos) -> Result<(), DeviceError> {
        self.call("move_to")?;
        self.inner.move_to(target)
    }
    fn move_to_or_abort(&mut self, target: Pos, abort: &AtomicBool) -> Result<bool, DeviceError> {
        self.call("move_to")?;
        self.inner.move_to_or_abort(target, abort)
    }
    fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError> {
        self.inner.travel_range()
    }
    fn stop(&mut self) -> Result<(), DeviceError> {
        self.call("stop")?;
        self.inner.stop()
    }
    fn move_time_s(&self) -> f64 {
        self.inner.move_time_s()
    }
    fn link_costs(&mut self) -> LinkCosts {
        self.inner.link_costs()
    }
    fn capabilities(&mut self, kind: CapabilityKind) -> Option<Capability<'_>> {
        match kind {
            CapabilityKind::Lines => Some(Capability::Lines(self)),
            _ => None,
        }
    }
}

/// The inner stage's lines, each call counted (and failed when told to).
impl LineScan for Tap {
    fn line_timing(&mut self) -> Result<Option<LineTiming>, DeviceError> {
        self.inner.line_timing()
    }
    fn configure_line(&mut self, s: &LineSweep) -> Result<(), DeviceError> {
        self.call("configure_line")?;
        self.inner.lines_for("configure_line")?.configure_line(s)
    }
    fn start_line(&mut self, s: &LineSweep) -> Result<(), DeviceError> {
        self.call("start_line")?;
        self.inner.lines_for("start_line")?.start_line(s)
    }
    fn wait_line(&mut self, s: &LineSweep, abort: &AtomicBool) -> Result<bool, DeviceError> {
        self.inner.lines_for("wait_line")?.wait_line(s, abort)
    }
    fn read_line_record(&mut self, s: &LineSweep) -> Result<SweepRecord, DeviceError> {
        self.call("read_line_record")?;
        self.inner
            .lines_for("read_line_record")?
            .read_line_record(s)
    }
    fn stop_line(&mut self, s: &LineSweep) -> Result<(), DeviceError> {
        self.call("stop_line")?;
        self.inner.stop_line(s)
    }
}

/// One 110 nm polystyrene bead at (0.1, 0, 0) µm, no effects: a deterministic scene.
fn core() -> SimCore {
    let mut scene = Scene::default();
    let bead = Bead {
        pos: [0.1, 0.0, 0.0],
        d_nm: 110.0,
        n: 1.572,
    };
    scene.add_bead(bead).unwrap();
    SimCore::new(&Optics::default(), &scene, SimConfig::default()).unwrap()
}

/// An instrument of `backend` at `START`, its soft limits, and the emulators (kept alive).
fn instrument(backend: Backend) -> (Instrument, SoftLimits, Option<Emulated>) {
    let core = core();
    let (mut inst, limits, emu) = match backend {
        Backend::Sim => (core.instrument(0.002), SoftLimits::default(), None),
        Backend::Emulated => {
            let mut base = Config::from_toml_str("[stage]\nsettle_s = 0.0\n", "t").unwrap();
            base.stage.settle_s = 0.002;
            let mut e = connect_emulated_redpitaya(
                core.renderer(),
                &core.cfg,
                &base,
                0.0,
                EmulatedStageLink::Pty,
            )
            .unwrap();
            // the emulated instrument is moved out; the emulators stay alive in `e`
            let inst = std::mem::replace(&mut e.connected.instrument, core.instrument(0.0));
            (inst, e.connected.limits, Some(e))
        }
    };
    inst.move_settle(START).unwrap();
    (inst, limits, emu)
}

/// A relative 8 × 4 raster of ±0.5 µm × ±0.3 µm around the start, 1 ms per pixel.
fn plan() -> Plan {
    Plan::grid(
        "scan_xy",
        Sweep::new("scan_xy", Axis::X, -0.5, 0.5, NX as i64, "nx").unwrap(),
        Sweep::new("scan_xy", Axis::Y, -0.3, 0.3, NY as i64, "ny").unwrap(),
        vec![],
        1e-3,
        true,
        false,
    )
    .unwrap()
}

struct Outcome {
    run: ScanRun,
    calls: Vec<&'static str>,
    pauses: Vec<(usize, usize, Pos)>,
    /// The stage's commanded target after the scan.
    end: Pos,
    emu: Option<Emulated>,
}

/// What a run injects.
#[derive(Default, Clone, Copy)]
struct Inject {
    /// Ctrl-C during this stage call (name, count).
    ctrl_c: Option<(&'static str, usize)>,
    /// The pause question's answer (`None`: no question, Ctrl-C aborts).
    answer: Option<bool>,
    /// This stage call fails (the simulator).
    fail: Option<(&'static str, usize)>,
    /// The emulated controller rejects a command: (word, commands of that word served before
    /// it, error code).
    reject: Option<(&'static str, usize, i64)>,
}

/// Run `plan()` in `mode` on `backend` with what `inj` injects.
fn go(tag: &str, mode: Mode, backend: Backend, inj: Inject) -> Outcome {
    let Inject {
        ctrl_c,
        answer,
        fail,
        reject,
    } = inj;
    let (mut inst, limits, emu) = instrument(backend);
    if let (Some(e), Some((w, n, code))) = (&emu, reject) {
        e.stage.faults().reject = Some((w.into(), n, code));
    }
    let abort = Arc::new(AtomicBool::new(false));
    let calls: Calls = Arc::default();
    let inner = std::mem::replace(&mut inst.stage, core().instrument(0.0).stage);
    inst.stage = Box::new(Tap {
        inner,
        calls: calls.clone(),
        abort: abort.clone(),
        ctrl_c,
        fail,
    });
    let dir = std::env::temp_dir().join(format!(
        "bfpscope-stoprule-{}-{tag}-{mode:?}-{backend:?}",
        std::process::id()
    ));
    cleanup::at_exit(&dir);
    let _ = std::fs::remove_dir_all(&dir);
    let store = SessionStore::new(dir);
    let save = move |s: &bfpscope::data::Scan| store.autosave(s).map_err(|e| e.to_string());
    let log = |_: &str| {};
    let pauses = Mutex::new(vec![]);
    let ask = |p: &Paused| {
        assert!(
            !abort.load(Ordering::SeqCst),
            "the flag is cleared while asking"
        );
        pauses.lock().unwrap().push((p.measured, p.total, p.at));
        answer.unwrap_or(false)
    };
    let env = ScanEnv {
        pause: answer.map(|_| &ask as &dyn Fn(&Paused) -> bool),
        ..ScanEnv::plain(&limits, &abort, &log, &save)
    };
    let mut strategy = mode.strategy();
    let run = run(&mut inst, &plan(), strategy.as_mut(), &env).unwrap();
    let end = inst.stage.target().unwrap();
    let calls = calls.lock().unwrap().clone();
    Outcome {
        run,
        calls,
        pauses: pauses.into_inner().unwrap(),
        end,
        emu,
    }
}

/// Rows of the saved scan with every pixel measured, and with none (the rest must be none).
fn measured_rows(o: &Outcome) -> usize {
    let s = load_scan(o.run.saved.as_ref().unwrap()).unwrap();
    assert_eq!(s.status, o.run.scan.status);
    let d = &s.sx.data;
    let mut n = 0;
    for r in 0..NY {
        let row = d.row(r);
        let finite = row.iter().filter(|v| v.is_finite()).count();
        assert!(
            finite == 0 || finite == NX || n == r,
            "row {r}: {finite} pixels"
        );
        n += usize::from(finite > 0);
    }
    let finite = d.iter().filter(|v| v.is_finite()).count();
    assert_eq!(
        finite,
        o.run.scan.meta["points_measured"].as_u64().unwrap() as usize
    );
    n
}

/// Motion commands in `cmds` (the emulated PI controller's log).
fn moves(cmds: &[String]) -> Vec<&String> {
    cmds.iter()
        .filter(|c| {
            let w = c.split_whitespace().next().unwrap_or("");
            ["MOV", "MVR", "SVO", "VEL", "WAV"].contains(&w) || (w == "WGO" && c.ends_with(" 1"))
        })
        .collect()
}

fn pause_then_resume(mode: Mode, backend: Backend) {
    let what = format!("{mode:?} on {backend:?}");
    let plain = go("plain", mode, backend, Inject::default());
    assert_eq!(plain.run.ended, Ended::Complete, "{what}");
    let ctrl_c = Some(mode.ctrl_c_at());
    let resume = Inject {
        ctrl_c,
        answer: Some(true),
        ..Inject::default()
    };
    let o = go("resume", mode, backend, resume);
    assert_eq!(o.run.ended, Ended::Complete, "{what}");
    // one pause, between steps, after the step during which Ctrl-C came
    assert_eq!(o.pauses.len(), 1, "{what}");
    let (measured, total, at) = o.pauses[0];
    assert_eq!(
        (measured, total),
        (mode.measured_at_stop(), NX * NY),
        "{what}"
    );
    let p = &o.run.scan.meta["pauses"][0];
    assert_eq!(p["after_points"], measured as u64, "{what}");
    assert_eq!(p["resumed"], true, "{what}");
    match mode {
        Mode::Points => {
            // the stage waited on the 11th point: row 1 (y = −0.1 µm rel.), column 2
            let want = [START[0] - 0.5 + 2.0 / 7.0, START[1] - 0.1, 0.0];
            for k in 0..3 {
                assert!(
                    (at[k] - want[k]).abs() < 1e-12,
                    "{what}: {at:?} vs {want:?}"
                );
            }
            // nothing but the 32 moves and the return: the pause commanded nothing
            assert_eq!(o.calls.iter().filter(|c| **c == "move_to").count(), 32 + 1);
            assert!(!o.calls.contains(&"stop"), "{what}: {:?}", o.calls);
        }
        Mode::Raster => {
            // the 2nd line finished, then the generator off (stop_line), then the 3rd line's
            // wave configured again before it started
            let starts: Vec<usize> = (0..o.calls.len())
                .filter(|&i| o.calls[i] == "start_line")
                .collect();
            assert_eq!(starts.len(), NY, "{what}: {:?}", o.calls);
            let between = &o.calls[starts[1]..starts[2]];
            let rec = between.iter().position(|c| *c == "read_line_record");
            let stop = between.iter().position(|c| *c == "stop_line");
            let conf = between.iter().position(|c| *c == "configure_line");
            assert!(
                matches!((rec, stop, conf), (Some(a), Some(b), Some(c)) if a < b && b < c),
                "{what}: {between:?}"
            );
            // the stage held at the end of the 2nd line's wave (row 2: y = −0.1 µm rel.),
            // past the field's +x edge
            assert!(at[0] > START[0] + 0.5 && (at[1] - (START[1] - 0.1)).abs() < 1e-12);
        }
    }
    if let Some(e) = &o.emu {
        let cmds = e.stage.commands();
        if mode == Mode::Raster {
            // the pause on the wire: the board stopped, `WGO 1 0` and `STP` between the 2nd
            // and the 3rd `WGO 1 1`
            let starts: Vec<usize> = (0..cmds.len()).filter(|&i| cmds[i] == "WGO 1 1").collect();
            let between = &cmds[starts[1]..starts[2]];
            assert!(
                between.iter().any(|c| c == "WGO 1 0") && between.iter().any(|c| c == "STP"),
                "{what}: {between:?}"
            );
            assert!(e.qpd.commands().iter().any(|c| c == "ACQ:STOP"), "{what}");
        } else {
            assert!(!cmds.iter().any(|c| c == "STP"), "{what}");
        }
    }
    // the scan equals the uninterrupted one
    let worst = [
        (&o.run.scan.sx, &plain.run.scan.sx),
        (&o.run.scan.sy, &plain.run.scan.sy),
        (&o.run.scan.sz, &plain.run.scan.sz),
    ]
    .iter()
    .flat_map(|(a, b)| a.data.iter().zip(b.data.iter()).map(|(x, y)| (x - y).abs()))
    .fold(0.0f64, f64::max);
    let peak = plain
        .run
        .scan
        .sx
        .data
        .iter()
        .fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(peak > 1e-3, "{what}: {peak}");
    // the simulator is deterministic, and so are the emulators' point reads on target: the same
    // numbers. The emulated Red Pitaya's raster is not: its decimator runs free, so a sample is
    // dated within ±dt/2 of its true time, a phase drawn anew at every arm (docs/hardware.md
    // §11), and two runs bin the same line up to v·dt = pitch / samples-per-pixel apart. A pixel
    // then moves by at most |∂S/∂x|·pitch/spp: bounded by the largest difference between
    // neighbouring pixels over spp (20 asked; the board gives at least that many), × 1.5 for the
    // tangent steeper than the secant.
    let tol = match (mode, backend) {
        (Mode::Raster, Backend::Emulated) => {
            let step = [&plain.run.scan.sx, &plain.run.scan.sy, &plain.run.scan.sz]
                .iter()
                .flat_map(|img| {
                    img.data
                        .rows()
                        .into_iter()
                        .flat_map(|r| {
                            r.to_vec()
                                .windows(2)
                                .map(|w| (w[1] - w[0]).abs())
                                .collect::<Vec<_>>()
                        })
                        .collect::<Vec<_>>()
                })
                .fold(0.0f64, f64::max);
            1.5 * step / bfpscope::acquire::raster::DEFAULT_SAMPLES_PER_PIXEL as f64
        }
        _ => 0.0,
    };
    eprintln!("{what}: pause + resume vs uninterrupted: worst pixel difference {worst:.3e} (Sx peak {peak:.3e})");
    assert!(
        worst <= tol,
        "{what}: worst pixel difference {worst} (peak {peak})"
    );
    assert!(o.run.returned_to_start, "{what}");
    assert_eq!(o.end, START, "{what}");
}

fn pause_then_abort(mode: Mode, backend: Backend) {
    let what = format!("{mode:?} on {backend:?}");
    let abort = Inject {
        ctrl_c: Some(mode.ctrl_c_at()),
        answer: Some(false),
        ..Inject::default()
    };
    let o = go("abort", mode, backend, abort);
    let measured = mode.measured_at_stop();
    assert_eq!(o.run.ended, Ended::Aborted { measured }, "{what}");
    assert_eq!(o.run.scan.status, ScanStatus::Aborted, "{what}");
    assert_eq!(o.pauses.len(), 1, "{what}");
    // the relative scan went back to its start, and that was its last move
    assert!(o.run.returned_to_start, "{what}");
    assert_eq!(o.end, START, "{what}");
    assert_eq!(o.calls.last(), Some(&"move_to"), "{what}: {:?}", o.calls);
    // the partial scan on disk: the rows measured, the others NaN
    let rows = measured_rows(&o);
    assert_eq!(rows, measured.div_ceil(NX), "{what}");
    let msg = o.run.summary().unwrap_err();
    assert!(
        msg.contains(&format!(
            "aborted (Ctrl-C) after {measured} of 32 points; returned to start"
        )) && msg.contains("partial scan (status aborted) saved to"),
        "{what}: {msg}"
    );
    if let (Some(e), Mode::Raster) = (&o.emu, mode) {
        // the raster was stopped before the return: `WGO 1 0`, `STP`, then the `MOV`
        let cmds = e.stage.commands();
        let stp = cmds.iter().rposition(|c| c == "STP").expect("STP");
        assert!(
            cmds[..stp].iter().rev().take(4).any(|c| c == "WGO 1 0"),
            "{what}"
        );
        assert_eq!(moves(&cmds[stp..]).len(), 1, "{what}: {:?}", &cmds[stp..]);
    }
}

fn stage_fault(mode: Mode, backend: Backend) {
    let what = format!("{mode:?} on {backend:?}");
    // the 11th point's move or the 3rd line's recorder read fails
    let (fail, reject) = match (backend, mode) {
        (Backend::Sim, Mode::Points) => (Some(("move_to", 11)), None),
        (Backend::Sim, Mode::Raster) => (Some(("read_line_record", 3)), None),
        (Backend::Emulated, Mode::Points) => (None, Some(("MOV", 10, 7))),
        (Backend::Emulated, Mode::Raster) => (None, Some(("DRR?", 2, 77))),
    };
    let inj = Inject {
        fail,
        reject,
        ..Inject::default()
    };
    let o = go("fault", mode, backend, inj);
    let measured = match mode {
        Mode::Points => 10,
        Mode::Raster => 2 * NX,
    };
    let (error, stage) = match &o.run.ended {
        Ended::Failed {
            measured: m,
            error,
            stage_fault,
        } => {
            assert_eq!(*m, measured, "{what}");
            (error.to_string(), *stage_fault)
        }
        other => panic!("{what}: {other:?}"),
    };
    assert!(stage, "{what}: {error}");
    assert_eq!(o.run.scan.status, ScanStatus::Failed, "{what}");
    // the stop went out; nothing that moves came after the fault (no return, no park move)
    let failing = match mode {
        Mode::Points => "move_to",
        Mode::Raster => "read_line_record",
    };
    let last = o.calls.iter().rposition(|c| *c == failing).unwrap();
    let after = &o.calls[last + 1..];
    let stop = if mode == Mode::Points {
        "stop"
    } else {
        "stop_line"
    };
    assert_eq!(after, [stop], "{what}: {:?}", o.calls);
    assert!(!o.run.returned_to_start, "{what}");
    assert_eq!(o.run.scan.meta["stop_sent"], true, "{what}");
    assert_eq!(o.run.scan.meta["error"]["stage_fault"], true, "{what}");
    // the partial scan on disk
    assert_eq!(measured_rows(&o), measured.div_ceil(NX), "{what}");
    let msg = o.run.summary().unwrap_err();
    assert!(
        msg.contains(&format!("failed after {measured} of 32 points"))
            && msg.contains("the stage was not commanded further, but for a stop")
            && msg.contains("partial scan (status failed) saved to")
            && !msg.contains("returned to start"),
        "{what}: {msg}"
    );
    match &o.emu {
        None => assert!(msg.contains("(injected)"), "{what}: {msg}"),
        Some(e) => {
            // the controller's own words; on the wire: the rejected command, `STP`, no motion
            let (cmd, code) = match mode {
                Mode::Points => ("MOV", "controller error 7"),
                Mode::Raster => ("DRR?", "controller error 77"),
            };
            assert!(
                msg.contains("PI E-727 on /dev/pts/") && msg.contains(code) && msg.contains(cmd),
                "{what}: {msg}"
            );
            let cmds = e.stage.commands();
            let bad = cmds
                .iter()
                .rposition(|c| c.starts_with(&format!("{cmd} ")))
                .unwrap();
            let tail = &cmds[bad..];
            assert!(tail.iter().any(|c| c == "STP"), "{what}: {tail:?}");
            let moved: Vec<_> = moves(&tail[1..]);
            assert!(
                moved.is_empty(),
                "{what}: motion after the fault: {moved:?}"
            );
        }
    }
}

/// The table: every case through every mode on every backend.
#[test]
fn the_stop_rule_holds_for_every_mode_and_backend() {
    for backend in [Backend::Sim, Backend::Emulated] {
        for mode in [Mode::Points, Mode::Raster] {
            for case in [Case::PauseResume, Case::PauseAbort, Case::StageFault] {
                match case {
                    Case::PauseResume => pause_then_resume(mode, backend),
                    Case::PauseAbort => pause_then_abort(mode, backend),
                    Case::StageFault => stage_fault(mode, backend),
                }
            }
        }
    }
}
