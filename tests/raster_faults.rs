//! Hardware-timed rasters through the engine (`acquire::run_raster`) on the emulated
//! PI stage (GCS over a pseudo-terminal or loopback TCP) and Red Pitaya board (loopback TCP),
//! OUT1 wired to the board's external trigger: a complete raster images the simulated scene,
//! and each fault a hardware-timed raster can meet (a silent digitiser, a trigger that never comes, a data-recorder
//! read that fails) ends with the wave generator off (`WGO 1 0`), the axes stopped (`STP`), no
//! motion after the stop, the completed lines in the autosaved file and a message naming the
//! device, the command and the reply; Ctrl-C mid-line finishes the line first (the stop rule
//! of every mode: tests/stop_rule.rs).

use crate::support::cleanup;

use bfpscope::acquire::raster::RasterOptions;
use bfpscope::acquire::run_raster;
use bfpscope::acquire::{Axis, Ended, Plan, ScanEnv, ScanError, ScanRun, SoftLimits, Sweep};
use bfpscope::config::connect::{connect_emulated_redpitaya, Emulated, EmulatedStageLink};
use bfpscope::config::Config;
use bfpscope::data::npz::{load_scan, save_scan};
use bfpscope::data::{Scan, ScanStatus};
use bfpscope::instrument::emulator::Emulator;
use bfpscope::instrument::sim::scene::{Bead, Scene};
use bfpscope::instrument::sim::{SimConfig, SimCore};
use bfpscope::optics::params::Optics;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

const NX: i64 = 16;
const NY: i64 = 6;

fn core() -> SimCore {
    let mut scene = Scene::default();
    scene
        .add_bead(Bead {
            pos: [0.0; 3],
            d_nm: 110.0,
            n: 1.572,
        })
        .unwrap();
    SimCore::new(&Optics::default(), &scene, SimConfig::default()).unwrap()
}

fn setup(link: EmulatedStageLink, settle_s: f64) -> (SimCore, Emulated) {
    let core = core();
    let mut base = Config::from_toml_str("[stage]\nsettle_s = 0.0\n", "t").unwrap();
    base.stage.settle_s = settle_s;
    let e = connect_emulated_redpitaya(core.renderer(), &core.cfg, &base, 1e-4, link).unwrap();
    (core, e)
}

fn plan(dwell_s: f64) -> Plan {
    Plan::grid(
        "scan_xy",
        Sweep::new("scan_xy", Axis::X, -0.5, 0.5, NX, "nx").unwrap(),
        Sweep::new("scan_xy", Axis::Y, -0.5, 0.5, NY, "ny").unwrap(),
        vec![],
        dwell_s,
        false,
        false,
    )
    .unwrap()
}

/// Run the raster with `abort`, autosaving to a fresh file; the result and the file.
fn run(
    e: &mut Emulated,
    plan: &Plan,
    abort: &AtomicBool,
    tag: &str,
) -> (Result<ScanRun, ScanError>, PathBuf) {
    let dir = std::env::temp_dir().join(format!("bfpscope-rasterhw-{tag}-{}", std::process::id()));
    cleanup::at_exit(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("scan_0001.npz");
    let _ = std::fs::remove_file(&path);
    let limits: SoftLimits = e.connected.limits;
    let log = |_: &str| {};
    let p = path.clone();
    let save = move |s: &Scan| -> Result<PathBuf, String> {
        save_scan(&p, s).map_err(|e| e.to_string())?;
        Ok(p.clone())
    };
    let env = ScanEnv::plain(&limits, abort, &log, &save);
    let r = run_raster(
        &mut e.connected.instrument,
        plan,
        &RasterOptions::default(),
        &env,
    );
    (r, path)
}

/// Raise `then` when `emu` has logged `word` `n` times (a watcher thread).
fn when_logged(emu: &Emulator, word: &'static str, n: usize, then: impl FnOnce() + Send + 'static) {
    let log = emu.command_log();
    std::thread::spawn(move || {
        for _ in 0..20_000 {
            if log().iter().filter(|c| c.as_str() == word).count() >= n {
                then();
                return;
            }
            std::thread::sleep(Duration::from_micros(500));
        }
    });
}

/// After the `n`-th `WGO 1 1`: `WGO 1 0` and `STP`, and nothing that moves after the `STP`.
fn assert_stopped_after_line(stage: &Emulator, n: usize) {
    let log = stage.commands();
    let starts: Vec<usize> = log
        .iter()
        .enumerate()
        .filter(|(_, c)| c.as_str() == "WGO 1 1")
        .map(|(i, _)| i)
        .collect();
    assert_eq!(starts.len(), n, "lines started: {starts:?}");
    let tail = &log[starts[n - 1]..];
    let wgo0 = tail.iter().position(|c| c == "WGO 1 0");
    let stp = tail.iter().position(|c| c == "STP");
    assert!(
        matches!((wgo0, stp), (Some(a), Some(b)) if a < b),
        "no `WGO 1 0` then `STP` after line {n}: {tail:?}"
    );
    let after = &tail[stp.unwrap()..];
    for c in after {
        let w = c.split_whitespace().next().unwrap_or("");
        assert!(
            !["MOV", "MVR", "WGO", "SVO", "VEL", "WAV"].contains(&w) || c == "WGO 1 0",
            "motion command `{c}` after the stop: {after:?}"
        );
    }
}

/// The generator is off and the axes at rest: `WGO? 1` = 0, every axis on target and two
/// position reads 20 ms apart equal.
fn assert_at_rest(e: &mut Emulated) {
    let st = &mut e.connected.instrument.stage;
    assert_eq!(st.raw_query("WGO? 1").unwrap(), vec!["1=0".to_string()]);
    assert_eq!(
        st.raw_query("ONT? 1 2 3").unwrap(),
        vec!["1=1".to_string(), "2=1".into(), "3=1".into()]
    );
    let a = st.position().unwrap();
    std::thread::sleep(Duration::from_millis(20));
    assert_eq!(a, st.position().unwrap());
}

/// The file on disk: rows before `done` measured, the others NaN, with `status`.
fn assert_file(path: &PathBuf, done: usize, status: ScanStatus) {
    let s = load_scan(path).unwrap();
    assert_eq!(s.status, status);
    let d = &s.sx.data;
    assert_eq!(d.dim(), (NY as usize, NX as usize));
    for r in 0..NY as usize {
        for c in 0..NX as usize {
            assert_eq!(
                d[[r, c]].is_finite(),
                r < done,
                "row {r} col {c}: {} ({done} rows done)",
                d[[r, c]]
            );
        }
    }
    // the raw samples of the completed lines are kept (rows of lines not measured: NaN)
    let raw = &s.raw.iter().find(|(n, _)| n == "sx").expect("raw_sx").1;
    for (r, row) in raw.rows().into_iter().enumerate() {
        assert_eq!(
            row.iter().any(|v| v.is_finite()),
            r < done,
            "raw_sx row {r} ({done} rows done)"
        );
    }
}

#[test]
fn a_raster_through_the_drivers_images_the_scene() {
    for link in [EmulatedStageLink::Pty, EmulatedStageLink::Tcp] {
        let (core, mut e) = setup(link, 0.002);
        let p = plan(1e-3);
        let (r, path) = run(&mut e, &p, &AtomicBool::new(false), "ok");
        let r = r.unwrap();
        assert_eq!(r.ended, Ended::Complete);
        assert_eq!(r.scan.meta["mode"], "raster");
        assert_eq!(r.scan.meta["raster"]["trigger_line"], 1);
        // the ideal image of the same scene, pixel by pixel
        let want = core
            .renderer()
            .render_grid_ideal(&r.scan.sx.x, &r.scan.sx.y, 0.0);
        let peak = want[0].iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(peak > 1e-3, "{peak}");
        let mut worst = 0.0f64;
        for (c, img) in [&r.scan.sx, &r.scan.sy, &r.scan.sz].iter().enumerate() {
            for ((row, col), v) in img.data.indexed_iter() {
                let w = want[c][row * NX as usize + col];
                worst = worst.max((v - w).abs() / peak);
            }
        }
        // a binned pixel is the mean over its pitch (0.067 µm) of a response about 0.3 µm
        // wide, the ideal image its value at the centre: they differ by the curvature term
        // f''·pitch²/24, measured 1.4 % of the Sx peak (noise: 1e-4 V per ADC sample, ≪)
        assert!(
            worst < 0.02,
            "{link:?}: worst difference {worst} of the Sx peak"
        );
        assert_file(&path, NY as usize, ScanStatus::Complete);
        let log = e.stage.commands();
        assert_eq!(log.iter().filter(|c| *c == "WGO 1 1").count(), NY as usize);
        assert!(!log.iter().any(|c| c == "STP"), "no stop in a good raster");
        assert!(e.qpd.commands().iter().any(|c| c == "ACQ:TRIG EXT_PE"));
    }
}

/// The error of a failed raster, its text.
fn failure(r: Result<ScanRun, ScanError>, done_pixels: usize) -> String {
    let r = r.unwrap();
    match &r.ended {
        Ended::Failed {
            measured, error, ..
        } => {
            assert_eq!(*measured, done_pixels);
            assert_eq!(r.scan.meta["error"]["message"], error.to_string());
            error.to_string()
        }
        other => panic!("{other:?}"),
    }
}

/// Ctrl-C during a line (a script: no pause question, Ctrl-C aborts): the line is finished
/// and kept, then the board, the generator and the axes are stopped; an absolute raster stays
/// where it stopped (a relative one returns: tests/stop_rule.rs).
#[test]
fn ctrl_c_mid_line_finishes_the_line_then_stops_the_generator_and_the_axes() {
    // 5 ms per pixel: a line of 16 pixels lasts over 80 ms; Ctrl-C during the third
    let (_core, mut e) = setup(EmulatedStageLink::Pty, 0.002);
    let abort = Arc::new(AtomicBool::new(false));
    let a = abort.clone();
    when_logged(&e.stage, "WGO 1 1", 3, move || {
        a.store(true, Ordering::SeqCst)
    });
    let (r, path) = run(&mut e, &plan(5e-3), &abort, "ctrlc");
    let r = r.unwrap();
    assert_eq!(
        r.ended,
        Ended::Aborted {
            measured: 3 * NX as usize
        }
    );
    assert_stopped_after_line(&e.stage, 3);
    // the third line's recorder read before the stop
    let log = e.stage.commands();
    let drr = log.iter().rposition(|c| c.starts_with("DRR? ")).unwrap();
    let stp = log.iter().rposition(|c| c == "STP").unwrap();
    assert!(drr < stp, "{:?}", &log[drr..]);
    assert!(e.qpd.commands().iter().any(|c| c == "ACQ:STOP"));
    assert_at_rest(&mut e);
    assert_file(&path, 3, ScanStatus::Aborted);
}

#[test]
fn a_silent_digitiser_stops_everything_and_names_the_board_and_command() {
    let (_core, mut e) = setup(EmulatedStageLink::Pty, 0.002);
    let faults = e.qpd.faults_handle();
    when_logged(&e.stage, "WGO 1 1", 3, move || {
        faults.lock().unwrap().silent = true;
    });
    let (r, path) = run(&mut e, &plan(1e-3), &AtomicBool::new(false), "silent");
    let msg = failure(r, 2 * NX as usize);
    assert!(
        msg.contains("Red Pitaya on 127.0.0.1:") && msg.contains("no reply to `ACQ:"),
        "{msg}"
    );
    assert_stopped_after_line(&e.stage, 3);
    assert_at_rest(&mut e);
    assert_file(&path, 2, ScanStatus::Failed);
}

#[test]
fn a_trigger_that_never_comes_stops_everything_and_names_the_state_query() {
    // 20 ms settle before each line: the switch is set between the 2nd line's record and the
    // 3rd line's start
    let (_core, mut e) = setup(EmulatedStageLink::Pty, 0.02);
    let faults = e.qpd.faults_handle();
    let log = e.stage.command_log();
    std::thread::spawn(move || {
        for _ in 0..20_000 {
            if log().iter().filter(|c| c.starts_with("DRR? ")).count() >= 2 {
                faults.lock().unwrap().no_trigger = true;
                return;
            }
            std::thread::sleep(Duration::from_micros(500));
        }
    });
    let (r, path) = run(&mut e, &plan(1e-3), &AtomicBool::new(false), "notrig");
    let msg = failure(r, 2 * NX as usize);
    assert!(
        msg.contains("Red Pitaya on 127.0.0.1:")
            && msg.contains("`ACQ:TRIG:STAT?` still answers \"WAIT\" (source EXT_PE"),
        "{msg}"
    );
    assert_stopped_after_line(&e.stage, 3);
    assert_at_rest(&mut e);
    assert_file(&path, 2, ScanStatus::Failed);
}

#[test]
fn a_failed_recorder_read_stops_everything_and_names_the_controller_error() {
    let (_core, mut e) = setup(EmulatedStageLink::Pty, 0.002);
    // the third line's `DRR?` is rejected with error 77
    e.stage.faults().reject = Some(("DRR?".into(), 2, 77));
    let (r, path) = run(&mut e, &plan(1e-3), &AtomicBool::new(false), "drr");
    let msg = failure(r, 2 * NX as usize);
    assert!(
        msg.contains("PI E-727 on /dev/pts/")
            && msg.contains("controller error 77 after `DRR? 1 ")
            && msg.contains("Data Record Table does not hold enough recorded data"),
        "{msg}"
    );
    assert_stopped_after_line(&e.stage, 3);
    assert_at_rest(&mut e);
    assert_file(&path, 2, ScanStatus::Failed);
}

#[test]
fn scan_xy_in_raster_mode_at_the_prompt_runs_through_the_emulated_red_pitaya() {
    use bfpscope::script::{Settings, Workbench};
    let dir = std::env::temp_dir().join(format!("bfpscope-rasterhw-wb-{}", std::process::id()));
    cleanup::at_exit(&dir);
    let (settings, _buf) = Settings::captured(&dir);
    let mut wb = Workbench::new(settings);
    let r = wb
        .eval_source(
            "t",
            r#"connect(#{backend: "emulated", qpd: "redpitaya", noise_v: 1e-4})"#,
        )
        .unwrap()
        .to_string();
    assert!(
        r.starts_with("connected emulated: PI E-727 on /dev/pts/")
            && r.contains("Red Pitaya on 127.0.0.1:"),
        "{r}"
    );
    let s = wb
        .eval_source(
            "t",
            r#"let s = scan_xy(#{x: [-0.5, 0.5], y: [-0.5, 0.5], nx: 12, ny: 4, dwell: 0.001, mode: "raster"});
               [s.meta.mode, s.meta.status, s.meta.raster.trigger_line, s.meta.instrument.backend]"#,
        )
        .unwrap()
        .to_string();
    assert_eq!(s, r#"["raster", "complete", 1, "emulated"]"#);
    let bad = wb
        .eval_source("t", r#"connect(#{backend: "emulated", qpd: "kpa101"})"#)
        .unwrap_err()
        .to_string();
    assert!(
        bad.contains(r#"connect: qpd = "kpa101" is not an emulated digitiser; allowed: "scpi" (default), "redpitaya""#),
        "{bad}"
    );
}
