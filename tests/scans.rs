//! Safety behaviours of the scan engine, one test each, on the mock instrument (the mock
//! stage records every command it is sent).

use crate::support::cleanup;

use bfpscope::acquire::store::{load_scan, SessionStore};
use bfpscope::acquire::{
    run_plan, Axis, Ended, Paused, Plan, ScanEnv, ScanError, SoftLimits, Sweep,
};
use bfpscope::config::Config;
use bfpscope::data::ScanStatus;
use bfpscope::instrument::mock::{mock_instrument, MockConfig};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

fn tmp(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("bfpscope-scans-{}-{tag}", std::process::id()));
    cleanup::at_exit(&d);
    let _ = std::fs::remove_dir_all(&d);
    d
}

struct Harness {
    limits: SoftLimits,
    abort: Arc<AtomicBool>,
    store: SessionStore,
    log: Arc<Mutex<Vec<String>>>,
}

impl Harness {
    fn new(tag: &str) -> Self {
        Self {
            limits: SoftLimits::default(),
            abort: Arc::default(),
            store: SessionStore::new(tmp(tag)),
            log: Arc::default(),
        }
    }
    fn run(
        &self,
        inst: &mut bfpscope::instrument::Instrument,
        plan: &Plan,
    ) -> Result<bfpscope::acquire::ScanRun, ScanError> {
        self.run_paused(inst, plan, None)
    }
    fn run_paused(
        &self,
        inst: &mut bfpscope::instrument::Instrument,
        plan: &Plan,
        pause: Option<&dyn Fn(&Paused) -> bool>,
    ) -> Result<bfpscope::acquire::ScanRun, ScanError> {
        let log = self.log.clone();
        let logf = move |s: &str| log.lock().unwrap().push(s.to_string());
        let store = self.store.clone();
        let save = move |s: &bfpscope::data::Scan| store.autosave(s).map_err(|e| e.to_string());
        let env = ScanEnv {
            meta: serde_json::json!({"script": {"path": "test"}}),
            pause,
            ..ScanEnv::plain(&self.limits, &self.abort, &logf, &save)
        };
        run_plan(inst, plan, &env)
    }
}

fn line(kind: &str, axis: Axis, from: f64, to: f64, n: i64, rel: bool) -> Plan {
    Plan::line(
        kind,
        Sweep::new(kind, axis, from, to, n, "n").unwrap(),
        0.001,
        rel,
    )
    .unwrap()
}

fn grid(nx: i64, ny: i64, rel: bool, snake: bool) -> Plan {
    Plan::grid(
        "scan_xy",
        Sweep::new("scan_xy", Axis::X, -0.5, 0.5, nx, "nx").unwrap(),
        Sweep::new("scan_xy", Axis::Y, -0.5, 0.5, ny, "ny").unwrap(),
        vec![],
        0.001,
        rel,
        snake,
    )
    .unwrap()
}

#[test]
fn out_of_limit_plan_is_refused_before_any_move() {
    let h = Harness::new("refused");
    let (mut inst, mock) = mock_instrument(MockConfig::default());
    let plan = line("ascan", Axis::X, 40.0, 60.0, 21, false);
    let e = h.run(&mut inst, &plan).unwrap_err();
    assert_eq!(
        e.to_string(),
        "ascan refused before any move: point 12 of 21: x = 51 µm is above the soft limit x ≤ 50 µm"
    );
    assert!(mock.moves().is_empty(), "moves sent: {:?}", mock.moves());
    assert_eq!(h.store.last_number(), 0, "a refused plan saves nothing");
}

#[test]
fn config_soft_limits_narrow_the_travel_range() {
    let mut h = Harness::new("config-limits");
    h.limits = Config::from_toml_str("[safety]\nsoft_limits = { z = [-2.0, 2.0] }", "t")
        .unwrap()
        .soft_limits();
    let (mut inst, mock) = mock_instrument(MockConfig::default());
    let plan = line("dscan", Axis::Z, -3.0, 3.0, 61, true);
    let e = h.run(&mut inst, &plan).unwrap_err().to_string();
    assert!(
        e.contains("point 1 of 61: z = -3 µm is below the soft limit z ≥ -2 µm"),
        "{e}"
    );
    assert!(mock.moves().is_empty());
}

#[test]
fn step_size_rule_refuses_coarse_plans() {
    let h = Harness::new("step");
    let (mut inst, mock) = mock_instrument(MockConfig::default());
    let plan = line("ascan", Axis::Y, -40.0, 40.0, 5, false);
    let e = h.run(&mut inst, &plan).unwrap_err().to_string();
    assert!(
        e.contains("step along y = 20 µm exceeds max_step_um = 10 µm"),
        "{e}"
    );
    assert!(mock.moves().is_empty());
}

#[test]
fn speed_limit_refuses_a_fast_plan_naming_the_values_and_snake_passes() {
    // mock: settle 1 ms, 100 kHz; dwell 1 ms → 2 ms per point. 11 × 11 raster over 1 µm:
    // steps of 0.1 µm → 50 µm/s; the fly-back from x = 0.5 to x = -0.5 one row up is
    // √(1 + 0.01) = 1.005 µm → 502.5 µm/s.
    let mut h = Harness::new("speed");
    h.limits = Config::from_toml_str("[safety]\nmax_speed_um_s = 100", "t")
        .unwrap()
        .soft_limits();
    assert_eq!(h.limits.max_speed_um_s, Some(100.0));
    let (mut inst, mock) = mock_instrument(MockConfig::default());
    let e = h
        .run(&mut inst, &grid(11, 11, false, false))
        .unwrap_err()
        .to_string();
    assert_eq!(
        e,
        "scan_xy refused before any move: from point 11 to point 12 of 121 the stage moves 1.005 µm in \
         settle 0.001 s + dwell 0.001 s = 0.002 s per point: 502.5 µm/s exceeds max_speed_um_s = 100 µm/s \
         ([safety] in bfpscope.toml; use a longer dwell or settle, or smaller steps); this is a row change: \
         a snake scan (snake: true) avoids the fly-back"
    );
    assert!(mock.moves().is_empty(), "moves sent: {:?}", mock.moves());
    assert_eq!(h.store.last_number(), 0, "a refused plan saves nothing");
    // the same raster as a snake: every move is one pitch, 50 µm/s
    let run = h.run(&mut inst, &grid(11, 11, false, true)).unwrap();
    assert_eq!(run.ended, Ended::Complete);
    let v = run.scan.meta["max_speed_between_points_um_s"]
        .as_f64()
        .unwrap();
    assert!((v - 50.0).abs() < 1e-9, "{v}");
    // exactly at the limit is allowed; just above is not (a line of 0.2 µm steps: 100 µm/s)
    let (mut inst, _) = mock_instrument(MockConfig::default());
    assert!(h
        .run(&mut inst, &line("ascan", Axis::X, 0.0, 1.0, 6, false))
        .is_ok());
    h.limits.max_speed_um_s = Some(99.9);
    let e = h
        .run(&mut inst, &line("ascan", Axis::X, 0.0, 1.0, 6, false))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("from point 1 to point 2 of 6 the stage moves 0.2 µm"),
        "{e}"
    );
    assert!(
        e.contains("100 µm/s exceeds max_speed_um_s = 99.9 µm/s"),
        "{e}"
    );
    assert!(!e.contains("row change"), "{e}");
}

#[test]
fn relative_scan_returns_to_start_after_completion() {
    let h = Harness::new("rel-complete");
    let (mut inst, mock) = mock_instrument(MockConfig {
        start: [1.0, 2.0, 0.5],
        ..MockConfig::default()
    });
    let run = h.run(&mut inst, &grid(5, 4, true, false)).unwrap();
    assert_eq!(run.ended, Ended::Complete);
    assert!(run.returned_to_start);
    assert_eq!(mock.position(), [1.0, 2.0, 0.5]);
    assert_eq!(mock.moves().last().unwrap(), "move 1 2 0.5");
    // axes are absolute stage positions
    assert_eq!(run.scan.sx.x[0], 0.5);
    assert_eq!(run.scan.sx.y[3], 2.5);
    assert!(run.scan.sx.data.iter().all(|v| v.is_finite()));
    assert!(
        h.log.lock().unwrap().iter().any(|l| l.contains("ETA")),
        "ETA printed: {:?}",
        h.log.lock().unwrap()
    );
}

#[test]
fn relative_scan_returns_to_start_after_ctrl_c_and_keeps_partial_data() {
    let h = Harness::new("abort");
    let (mut inst, mock) = mock_instrument(MockConfig {
        start: [3.0, -1.0, 0.0],
        abort_after_reads: Some((7, h.abort.clone())),
        ..MockConfig::default()
    });
    let run = h.run(&mut inst, &grid(4, 4, true, true)).unwrap();
    assert_eq!(run.ended, Ended::Aborted { measured: 7 });
    assert!(run.returned_to_start);
    assert_eq!(mock.position(), [3.0, -1.0, 0.0]);
    assert!(
        !h.abort.load(Ordering::SeqCst),
        "the engine clears the flag it acted on"
    );
    assert_eq!(run.scan.status, ScanStatus::Aborted);
    let finite = run.scan.sx.data.iter().filter(|v| v.is_finite()).count();
    assert_eq!(finite, 7);
    // snake: the 7 points are row 0 (4) + row 1 visited right to left (3): pixel (1, 0) is unmeasured
    assert!(run.scan.sx.data[[1, 0]].is_nan() && run.scan.sx.data[[1, 1]].is_finite());
    let path = run.saved.clone().unwrap();
    let saved = load_scan(&path).unwrap();
    assert_eq!(saved.status, ScanStatus::Aborted);
    assert_eq!(saved.meta["points_measured"], 7);
    assert_eq!(saved.sx.data.iter().filter(|v| v.is_nan()).count(), 9);
    let msg = run.summary().unwrap_err();
    assert!(
        msg.contains("aborted (Ctrl-C) after 7 of 16 points; returned to start"),
        "{msg}"
    );
}

#[test]
fn ctrl_c_pauses_a_scan_that_resumes_where_it_stopped() {
    let h = Harness::new("pause");
    let (mut inst, mock) = mock_instrument(MockConfig {
        start: [3.0, -1.0, 0.0],
        abort_after_reads: Some((7, h.abort.clone())),
        ..MockConfig::default()
    });
    let (m2, a2) = (mock.clone(), h.abort.clone());
    let asked = Mutex::new(vec![]);
    let ask = |p: &Paused| {
        // while the question is open the stage rests on the 7th point: row 0 (4 points), then
        // row 1 right to left (snake) to its 3rd point, column 1; nothing else was commanded
        asked
            .lock()
            .unwrap()
            .push((p.measured, p.total, p.at, m2.position()));
        assert_eq!(m2.moves().len(), 7, "{:?}", m2.moves());
        assert!(
            !a2.load(Ordering::SeqCst),
            "the flag is cleared while asking"
        );
        true
    };
    let run = h
        .run_paused(&mut inst, &grid(4, 4, true, true), Some(&ask))
        .unwrap();
    assert_eq!(run.ended, Ended::Complete);
    let asked = asked.into_inner().unwrap();
    assert_eq!(asked.len(), 1);
    let (measured, total, at, stage) = asked[0];
    assert_eq!((measured, total), (7, 16));
    // grid(4, 4, rel): x, y from −0.5 to 0.5 µm in 4 points around the start (3, −1)
    let x1 = 3.0 - 0.5 + 1.0 / 3.0;
    let y1 = -1.0 - 0.5 + 1.0 / 3.0;
    assert!(
        (at[0] - x1).abs() < 1e-12 && (at[1] - y1).abs() < 1e-12,
        "{at:?}"
    );
    assert_eq!(stage, at);
    // all 16 points measured, each once; the stage returned to the start
    assert!(run.scan.sx.data.iter().all(|v| v.is_finite()));
    assert_eq!(mock.moves().len(), 16 + 1, "16 points and the return");
    assert_eq!(mock.position(), [3.0, -1.0, 0.0]);
    let p = &run.scan.meta["pauses"];
    assert_eq!(p.as_array().unwrap().len(), 1, "{p}");
    assert_eq!(p[0]["after_points"], 7);
    assert_eq!(p[0]["resumed"], true);
    assert!(h
        .log
        .lock()
        .unwrap()
        .iter()
        .any(|l| l.contains("resumed at point 8 of 16")));
}

#[test]
fn a_paused_scan_answered_abort_ends_as_ctrl_c_did() {
    let h = Harness::new("pause-abort");
    let (mut inst, mock) = mock_instrument(MockConfig {
        start: [3.0, -1.0, 0.0],
        abort_after_reads: Some((7, h.abort.clone())),
        ..MockConfig::default()
    });
    let ask = |_: &Paused| false;
    let run = h
        .run_paused(&mut inst, &grid(4, 4, true, true), Some(&ask))
        .unwrap();
    assert_eq!(run.ended, Ended::Aborted { measured: 7 });
    assert!(run.returned_to_start);
    assert_eq!(mock.position(), [3.0, -1.0, 0.0]);
    assert_eq!(mock.moves().len(), 7 + 1);
    assert_eq!(run.scan.meta["pauses"][0]["resumed"], false);
    assert_eq!(run.scan.status, ScanStatus::Aborted);
}

#[test]
fn relative_scan_returns_to_start_after_a_qpd_error() {
    let h = Harness::new("qpd-error");
    let (mut inst, mock) = mock_instrument(MockConfig {
        start: [0.0, 0.0, 1.0],
        fail_read_after: Some(5),
        ..MockConfig::default()
    });
    let run = h
        .run(&mut inst, &line("dscan", Axis::Z, -0.5, 0.5, 11, true))
        .unwrap();
    match &run.ended {
        Ended::Failed {
            measured: 5,
            stage_fault: false,
            error,
        } => {
            assert!(
                error
                    .to_string()
                    .contains("mock QPD: no reply to `MEAS:QPD?`"),
                "{error}"
            )
        }
        other => panic!("{other:?}"),
    }
    assert!(run.returned_to_start);
    assert_eq!(mock.position(), [0.0, 0.0, 1.0]);
    let saved = load_scan(run.saved.as_ref().unwrap()).unwrap();
    assert_eq!(saved.status, ScanStatus::Failed);
    assert!(saved.meta["error"]["message"]
        .as_str()
        .unwrap()
        .contains("no reply"));
    let msg = run.summary().unwrap_err();
    assert!(
        msg.contains("failed after 5 of 11 points: mock QPD: no reply"),
        "{msg}"
    );
}

#[test]
fn stage_error_stops_commanding_the_stage_and_saves_the_partial_scan() {
    let h = Harness::new("stage-error");
    let (mut inst, mock) = mock_instrument(MockConfig {
        fail_move_after: Some(6),
        ..MockConfig::default()
    });
    let run = h.run(&mut inst, &grid(4, 3, true, false)).unwrap();
    assert!(
        matches!(
            run.ended,
            Ended::Failed {
                measured: 6,
                stage_fault: true,
                ..
            }
        ),
        "{:?}",
        run.ended
    );
    assert!(!run.returned_to_start);
    // after the failed move: the stop, and nothing else
    let cmds = mock.commands();
    assert!(
        cmds[cmds.len() - 2].starts_with("move") && cmds[cmds.len() - 1] == "stop",
        "commands after the failed move: {cmds:?}"
    );
    assert_eq!(
        mock.moves().len(),
        7,
        "6 good moves + the failed one, nothing after"
    );
    let saved = load_scan(run.saved.as_ref().unwrap()).unwrap();
    assert_eq!(saved.status, ScanStatus::Failed);
    assert_eq!(saved.sx.data.iter().filter(|v| v.is_finite()).count(), 6);
    let msg = run.summary().unwrap_err();
    assert!(
        msg.contains("mock stage: disconnected during `MOV"),
        "{msg}"
    );
    assert!(msg.contains("the stage was not commanded further"), "{msg}");
}

#[test]
fn snake_scan_stores_pixels_in_image_order() {
    let h = Harness::new("snake");
    let (mut a, _) = mock_instrument(MockConfig::default());
    let (mut b, _) = mock_instrument(MockConfig::default());
    let raster = h.run(&mut a, &grid(7, 5, false, false)).unwrap().scan;
    let snake = h.run(&mut b, &grid(7, 5, false, true)).unwrap().scan;
    assert_eq!(raster.sx.data, snake.sx.data);
    assert_eq!(raster.sz.data, snake.sz.data);
    // and the data is the mock's signal at the pixel positions
    let (sx, _, _) = bfpscope::instrument::mock::mock_signal([snake.sx.x[6], snake.sx.y[1], 0.0]);
    assert_eq!(snake.sx.data[[1, 6]], sx);
}

#[test]
fn autosave_numbering_never_overwrites() {
    let dir = tmp("numbering");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("scan_0003.npz"), "precious").unwrap();
    std::fs::write(dir.join("notes.txt"), "x").unwrap();
    let store = SessionStore::new(&dir);
    let h = Harness::new("numbering-src");
    let (mut inst, _) = mock_instrument(MockConfig::default());
    let scan = h
        .run(&mut inst, &line("ascan", Axis::X, 0.0, 1.0, 3, false))
        .unwrap()
        .scan;
    assert_eq!(store.next_scan_path(), dir.join("scan_0004.npz"));
    let p = store.autosave(&scan).unwrap();
    assert_eq!(p, dir.join("scan_0004.npz"));
    assert_eq!(
        std::fs::read_to_string(dir.join("scan_0003.npz")).unwrap(),
        "precious"
    );
    // concurrent writers: every scan gets its own file
    let paths: Vec<PathBuf> = std::thread::scope(|s| {
        let hs: Vec<_> = (0..4)
            .map(|_| {
                s.spawn(|| {
                    (0..10)
                        .map(|_| store.autosave(&scan).unwrap())
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        hs.into_iter().flat_map(|h| h.join().unwrap()).collect()
    });
    let mut uniq = paths.clone();
    uniq.sort();
    uniq.dedup();
    assert_eq!(uniq.len(), 40);
    assert_eq!(store.last_number(), 44);
    // no temporary files left behind: only the scans and notes.txt
    let tmp_left = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .filter(|n| n != "notes.txt" && bfpscope::data::session::scan_number(n).is_none())
        .count();
    assert_eq!(tmp_left, 0);
    let target = dir.join("scan_0004.npz");
    let before = std::fs::read(&target).unwrap();
    let e = bfpscope::acquire::store::save_scan(&target, &scan).unwrap_err();
    assert_eq!(e.kind(), std::io::ErrorKind::AlreadyExists);
    assert_eq!(
        e.to_string(),
        format!("{} exists; scans are never overwritten", target.display())
    );
    assert_eq!(
        std::fs::read(&target).unwrap(),
        before,
        "the file was left as it was"
    );
}

#[test]
fn metadata_records_plan_instrument_time_and_status() {
    let h = Harness::new("meta");
    let (mut inst, _) = mock_instrument(MockConfig {
        settle_s: 0.002,
        ..MockConfig::default()
    });
    let run = h.run(&mut inst, &grid(8, 8, false, false)).unwrap();
    let m = &run.scan.meta;
    assert_eq!(m["plan"]["kind"], "scan_xy");
    assert_eq!(m["plan"]["fast"]["n"], 8);
    assert_eq!(m["status"], "complete");
    assert_eq!(m["instrument"]["backend"], "mock");
    assert_eq!(m["script"]["path"], "test");
    // 64 points × (2 ms settle + 1 ms dwell)
    let t = m["time"]["instrument_s"].as_f64().unwrap();
    assert!((t - 64.0 * 0.003).abs() < 1e-9, "{t}");
    assert_eq!(m["time"]["clock"], "virtual");
    assert!(m["time"]["wall_start"].as_str().unwrap().ends_with('Z'));
    assert!(
        (m["time"]["eta_s"].as_f64().unwrap() - t).abs() < 1e-9,
        "ETA = actual time on the virtual clock"
    );
}

#[test]
fn simulated_scan_metadata_reports_the_render_pipeline() {
    use bfpscope::instrument::sim::scene::Bead;
    use bfpscope::instrument::sim::{Scene, SimConfig, SimCore};
    use bfpscope::optics::Optics;
    let h = Harness::new("pipeline");
    let mut scene = Scene::default();
    scene
        .add_bead(Bead {
            pos: [0.0, 0.0, 0.0],
            d_nm: 110.0,
            n: 1.572,
        })
        .unwrap();
    scene.effects.enable("detector_noise").unwrap();
    let core = SimCore::new(&Optics::default(), &scene, SimConfig::default()).unwrap();
    let mut inst = core.instrument(0.0);
    let run = h.run(&mut inst, &grid(4, 4, false, false)).unwrap();
    let stages = run.scan.meta["pipeline"]
        .as_array()
        .expect("pipeline in meta");
    let names: Vec<&str> = stages.iter().map(|s| s["name"].as_str().unwrap()).collect();
    // the default instrument: the aplanatic vector beam renders the bead
    assert_eq!(names, ["superposition", "vector_beam", "detector_noise"]);
    // 16 reads went through the superposition stage: it has spent some time
    assert!(stages[0]["seconds"].as_f64().unwrap() > 0.0, "{stages:?}");
    // the mock instrument has no pipeline and reports none
    let (mut mock, _) = mock_instrument(MockConfig::default());
    let run = h.run(&mut mock, &grid(2, 2, false, false)).unwrap();
    assert!(run.scan.meta.get("pipeline").is_none());
}

#[test]
fn simulated_scan_eta_includes_the_stage_move_time() {
    // The simulated stage takes 2 ms per move before the settle time: the ETA printed before a
    // scan must count it, and equal the instrument time the scan then takes on the virtual clock.
    use bfpscope::instrument::sim::scene::Bead;
    use bfpscope::instrument::sim::{Scene, SimConfig, SimCore};
    use bfpscope::optics::Optics;
    let h = Harness::new("eta");
    let mut scene = Scene::default();
    scene
        .add_bead(Bead {
            pos: [0.0, 0.0, 0.0],
            d_nm: 110.0,
            n: 1.572,
        })
        .unwrap();
    let core = SimCore::new(&Optics::default(), &scene, SimConfig::default()).unwrap();
    assert!(core.cfg.move_time_s > 0.0);
    let mut inst = core.instrument(0.005);
    let run = h.run(&mut inst, &grid(8, 8, false, false)).unwrap();
    let t = &run.scan.meta["time"];
    let (eta, took) = (
        t["eta_s"].as_f64().unwrap(),
        t["instrument_s"].as_f64().unwrap(),
    );
    assert!(
        (eta - took).abs() <= 0.01 * took,
        "ETA {eta} s, took {took} s"
    );
    assert!(
        h.log
            .lock()
            .unwrap()
            .iter()
            .any(|l| l.contains("move 2 ms")),
        "{:?}",
        h.log.lock().unwrap()
    );
}
