//! Hardware-timed raster scans on the simulator: a stage of finite bandwidth lags
//! its wave, the digitiser's samples are binned by the recorder's measured position, and the
//! image equals the point-by-point image of the same scene within the detector noise.

use bfpscope::acquire::raster::{bin_line, positions_at_samples, RasterOptions};
use bfpscope::acquire::run_raster;
use bfpscope::acquire::{
    run_plan, Axis, Ended, Plan, ScanEnv, ScanError, ScanObserver, ScanRun, ScanStart, SoftLimits,
    Sweep,
};
use bfpscope::analysis::fit::{fit_beads, FitOptions};
use bfpscope::analysis::template::{RefBead, Template};
use bfpscope::data::{Scan, ScanStatus};
use bfpscope::instrument::sim::scene::{Bead, DetectorNoise, StageBandwidth};
use bfpscope::instrument::sim::{Scene, SimConfig, SimCore};
use bfpscope::instrument::Instrument;
use bfpscope::optics::rayleigh::DetectorModel;
use bfpscope::optics::Optics;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

/// Detector noise per sample (the paper's level) and the simulator's detector rate.
const SIGMA: f64 = 2e-3;
const RATE: f64 = 1e5;
/// τ = 1/(2π·318 Hz) = 0.50 ms: the stage's lag.
const BANDWIDTH_HZ: f64 = 318.0;
const BEAD: (f64, f64) = (0.03, -0.02);

fn scene(noise: bool) -> Scene {
    let mut s = Scene::default();
    s.add_bead(Bead {
        pos: [BEAD.0, BEAD.1, 0.0],
        d_nm: 110.0,
        n: 1.572,
    })
    .unwrap();
    if noise {
        s.effects.detector_noise = Some(DetectorNoise {
            sigma_sample: SIGMA,
        });
    }
    s.effects.stage_bandwidth = Some(StageBandwidth { hz: BANDWIDTH_HZ });
    s
}

fn instrument(scene: &Scene) -> Instrument {
    SimCore::new(&Optics::default(), scene, SimConfig::default())
        .unwrap()
        .instrument(0.005)
}

fn plan(n: usize, half: f64, dwell: f64, snake: bool, rel: bool) -> Plan {
    let sw = |a| Sweep::new("scan_xy", a, -half, half, n as i64, "n").unwrap();
    Plan::grid(
        "scan_xy",
        sw(Axis::X),
        sw(Axis::Y),
        vec![],
        dwell,
        rel,
        snake,
    )
    .unwrap()
}

struct Run {
    limits: SoftLimits,
    abort: AtomicBool,
    log: Mutex<Vec<String>>,
}

impl Run {
    fn new() -> Run {
        Run {
            limits: SoftLimits::default(),
            abort: AtomicBool::new(false),
            log: Mutex::new(vec![]),
        }
    }

    fn go(
        &self,
        inst: &mut Instrument,
        plan: &Plan,
        raster: bool,
        observer: Option<&dyn ScanObserver>,
    ) -> Result<ScanRun, ScanError> {
        let log = |s: &str| self.log.lock().unwrap().push(s.to_string());
        let save = |_: &Scan| -> Result<PathBuf, String> { Ok(PathBuf::from("unsaved.npz")) };
        let env = ScanEnv {
            observer,
            ..ScanEnv::plain(&self.limits, &self.abort, &log, &save)
        };
        if raster {
            run_raster(inst, plan, &RasterOptions::default(), &env)
        } else {
            run_plan(inst, plan, &env)
        }
    }
}

fn template() -> Template {
    Template::from_optics(
        &Optics::default(),
        &DetectorModel::default(),
        RefBead::default(),
        0.02,
        0.0,
    )
    .unwrap()
}

/// The one bead fitted: (x, y, x_err, y_err), µm.
fn fit(scan: &Scan) -> (f64, f64, f64, f64) {
    let f = fit_beads(
        &scan.sx,
        &scan.sy,
        &template(),
        &FitOptions {
            n_beads: Some(1),
            ..FitOptions::default()
        },
    )
    .unwrap();
    let b = &f.beads[0];
    (b.x, b.y, b.x_err.unwrap(), b.y_err.unwrap())
}

/// rms of (a − b) / s over the pixels.
fn rms_normalised(a: &Scan, b: &Scan, s: f64) -> [f64; 2] {
    [(&a.sx, &b.sx), (&a.sy, &b.sy)].map(|(p, q)| {
        let d: Vec<f64> = p
            .data
            .iter()
            .zip(q.data.iter())
            .map(|(x, y)| (x - y) / s)
            .collect();
        (d.iter().map(|v| v * v).sum::<f64>() / d.len() as f64).sqrt()
    })
}

/// A 33 × 33 raster (50 nm pixels, 1 ms) of a 110 nm bead under a lagging stage against the
/// point-by-point scan of the same scene: the difference is the detector noise of both (each
/// pixel averages 100 detector samples in both modes: σ/√100 each, so the difference has
/// √2·σ/10), and the bead's fitted position agrees within 2 nm.
#[test]
fn raster_of_a_bead_matches_the_point_scan_within_the_noise() {
    let sc = scene(true);
    let r = Run::new();
    let p = plan(33, 0.8, 1e-3, false, false);
    let points = r.go(&mut instrument(&sc), &p, false, None).unwrap();
    let raster = r.go(&mut instrument(&sc), &p, true, None).unwrap();
    assert_eq!(raster.ended, Ended::Complete);
    let m = &raster.scan.meta["raster"];
    assert_eq!(m["samples_per_pixel_min"], 20, "{m}");
    assert_eq!(m["line_speed_um_s"].as_f64().unwrap(), 50.0);
    // the binned pixels' mean positions: within half a sample spacing (v/rate_dig = 2.5 nm)
    // of their centres, whatever the lag
    assert!(
        m["position_error_um_max"].as_f64().unwrap() < 1.25e-3 + 1e-9,
        "{m}"
    );
    let s = 2f64.sqrt() * SIGMA / (1e-3 * RATE).sqrt();
    // 1089 pixels: the rms of N(0, 1) has sd 1/√(2·1089) = 2.1 %; 4 sd
    for (c, v) in ["sx", "sy"]
        .iter()
        .zip(rms_normalised(&raster.scan, &points.scan, s))
    {
        assert!(
            (v - 1.0).abs() < 0.085,
            "{c}: rms difference {v} of the noise"
        );
    }
    // 10× the dwell: the noise is √10 lower, the fits are tight enough to compare at 2 nm
    let p = plan(33, 0.8, 1e-2, false, false);
    let points = r.go(&mut instrument(&sc), &p, false, None).unwrap();
    let raster = r.go(&mut instrument(&sc), &p, true, None).unwrap();
    let (xp, yp, exp, eyp) = fit(&points.scan);
    let (xr, yr, exr, eyr) = fit(&raster.scan);
    // the fits' own uncertainties must leave room for the 2 nm comparison
    assert!(
        exp.max(eyp).max(exr).max(eyr) < 0.5e-3,
        "{exp} {eyp} {exr} {eyr}"
    );
    assert!(
        (xr - xp).abs() < 2e-3 && (yr - yp).abs() < 2e-3,
        "raster ({xr}, {yr}) vs points ({xp}, {yp})"
    );
    // and both find the bead where the scene put it (4 σ)
    assert!(
        (xr - BEAD.0).abs() < 4.0 * exr && (yr - BEAD.1).abs() < 4.0 * eyr,
        "({xr}, {yr})"
    );
}

/// The stage trails its wave by v·dt/(exp(dt/τ) − 1) ≈ v·τ (24 nm at 50 µm/s). Binned by the
/// recorder's measured position, the image shows the bead where it is; the same samples
/// binned by the *commanded* position put it one lag further along the sweep.
#[test]
fn binning_by_measured_position_removes_the_stage_lag() {
    let sc = scene(false);
    let r = Run::new();
    let p = plan(33, 0.8, 1e-3, false, false);
    let raster = r.go(&mut instrument(&sc), &p, true, None).unwrap();
    let m = &raster.scan.meta["raster"];
    let (v, dt) = (50.0, 50e-6);
    let tau = 1.0 / (2.0 * std::f64::consts::PI * BANDWIDTH_HZ);
    let lag = v * dt / ((dt / tau).exp() - 1.0);
    let measured_lag = m["lag_um_mean"].as_f64().unwrap();
    assert!(
        (measured_lag - lag).abs() < 0.01 * lag,
        "{measured_lag} vs {lag}"
    );

    // re-bin the raw samples by the commanded position
    let raw = |n: &str| {
        raster
            .scan
            .raw
            .iter()
            .find(|(k, _)| k == n)
            .unwrap_or_else(|| panic!("raw_{n} missing"))
            .1
            .clone()
    };
    let (sx, sy, target) = (raw("sx"), raw("sy"), raw("record_target_um"));
    let rec_dt = m["record_sample_s"].as_f64().unwrap();
    let rate = m["sample_rate_hz"].as_f64().unwrap();
    let cols = raster.scan.sx.x.clone();
    let mut by_cmd = raster.scan.clone();
    for row in 0..33 {
        let valid = |a: &ndarray::Array2<f64>| -> Vec<f64> {
            a.row(row)
                .iter()
                .copied()
                .take_while(|v| v.is_finite())
                .collect()
        };
        let (x, y, t) = (valid(&sx), valid(&sy), valid(&target));
        let pos = positions_at_samples(&t, rec_dt, x.len(), 1.0 / rate, 0.5 / rate).unwrap();
        let bx = bin_line(&pos, &x, cols[0], cols[32], 33).unwrap();
        let by = bin_line(&pos, &y, cols[0], cols[32], 33).unwrap();
        for i in 0..33 {
            by_cmd.sx.data[[row, i]] = bx.mean[i];
            by_cmd.sy.data[[row, i]] = by.mean[i];
        }
    }
    let (xm, ym, _, _) = fit(&raster.scan);
    let (xc, yc, _, _) = fit(&by_cmd);
    // noise-free: the measured binning finds the bead to well under a nanometre
    assert!(
        (xm - BEAD.0).abs() < 0.5e-3 && (ym - BEAD.1).abs() < 0.5e-3,
        "({xm}, {ym})"
    );
    // by the command, shifted along the sweep (+x) by the lag, not across it
    assert!(
        (xc - xm - lag).abs() < 0.1 * lag,
        "shift {} vs lag {lag}",
        xc - xm
    );
    assert!((yc - ym).abs() < 0.5e-3, "{yc} vs {ym}");
}

/// Snake rasters sweep every other line backwards: the lag then points the other way, and
/// binning by the measured position still gives the same image.
#[test]
fn a_snake_raster_equals_a_one_way_raster() {
    let sc = scene(false);
    let r = Run::new();
    let one = r
        .go(
            &mut instrument(&sc),
            &plan(21, 0.5, 1e-3, false, false),
            true,
            None,
        )
        .unwrap();
    let snake = r
        .go(
            &mut instrument(&sc),
            &plan(21, 0.5, 1e-3, true, false),
            true,
            None,
        )
        .unwrap();
    // noise-free: the two images' pixels differ only by where in each pixel the samples fell
    // (≤ half a sample spacing, 1.25 nm, from the centre, either way); the bead is found at
    // the same place to a fraction of that
    let (x1, y1, _, _) = fit(&one.scan);
    let (x2, y2, _, _) = fit(&snake.scan);
    assert!(
        (x1 - x2).abs() < 0.3e-3 && (y1 - y2).abs() < 0.3e-3,
        "({x1}, {y1}) vs ({x2}, {y2})"
    );
    assert!((x1 - BEAD.0).abs() < 0.5e-3, "{x1}");
}

/// Observer that raises the abort flag (a Ctrl-C) once `after` lines have been handed over.
struct CtrlCAfter<'a> {
    rows_seen: Mutex<std::collections::BTreeSet<usize>>,
    after: usize,
    abort: &'a AtomicBool,
}

impl ScanObserver for CtrlCAfter<'_> {
    fn started(&self, _: &ScanStart) {}
    fn points(&self, pts: &[(usize, usize, [f64; 3])]) {
        let mut rows = self.rows_seen.lock().unwrap();
        rows.extend(pts.iter().map(|p| p.0));
        if rows.len() == self.after {
            self.abort.store(true, Ordering::SeqCst);
        }
    }
    fn ended(&self, _: &Scan, _: Option<&std::path::Path>) {}
}

/// Ctrl-C between lines (no pause question: a script's Ctrl-C aborts): the completed lines
/// are kept, the rest NaN, status aborted, and a relative raster returns to its start after
/// the wave generator was stopped (the stop rule of every mode, tests/stop_rule.rs).
#[test]
fn ctrl_c_keeps_the_completed_lines_and_returns_a_relative_raster_to_its_start() {
    let sc = scene(false);
    let r = Run::new();
    let obs = CtrlCAfter {
        rows_seen: Mutex::default(),
        after: 3,
        abort: &r.abort,
    };
    let mut inst = instrument(&sc);
    let start = inst.stage.target().unwrap();
    let run = r
        .go(
            &mut inst,
            &plan(11, 0.5, 1e-3, false, true),
            true,
            Some(&obs),
        )
        .unwrap();
    assert_eq!(run.ended, Ended::Aborted { measured: 33 });
    assert_eq!(run.scan.status, ScanStatus::Aborted);
    for row in 0..11 {
        let measured = run.scan.sx.data.row(row).iter().all(|v| v.is_finite());
        let empty = run.scan.sx.data.row(row).iter().all(|v| v.is_nan());
        assert!(if row < 3 { measured } else { empty }, "row {row}");
    }
    // the stop after the third line, then the return
    assert!(run.returned_to_start);
    assert_eq!(inst.stage.target().unwrap(), start);
    assert_eq!(
        run.scan.meta["stop"],
        "the wave generator and the axes were stopped after row 3"
    );
    let msg = run.summary().unwrap_err();
    assert!(
        msg.contains("aborted (Ctrl-C) after 33 of 121 points; returned to start"),
        "{msg}"
    );
}

/// Pre-flight: a stage without a wave generator, a line faster than the speed limit and a
/// waveform whose ramps leave the soft limits are refused before anything moves.
#[test]
fn raster_preflight_refuses_before_the_first_move() {
    let r = Run::new();
    // the mock stage has no wave generator
    let (mut mock, _handle) = bfpscope::instrument::mock::mock_instrument(
        bfpscope::instrument::mock::MockConfig::default(),
    );
    let e = r
        .go(&mut mock, &plan(5, 0.5, 1e-3, false, false), true, None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("needs a stage with a wave generator"), "{e}");

    let sc = scene(false);
    let mut inst = instrument(&sc);
    let before = inst.stage.position().unwrap();
    let slow = Run {
        limits: SoftLimits {
            max_speed_um_s: Some(20.0),
            ..SoftLimits::default()
        },
        ..Run::new()
    };
    // 0.1 µm pitch / 1 ms = 100 µm/s
    let e = slow
        .go(&mut inst, &plan(11, 0.5, 1e-3, false, false), true, None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("line speed 100.0000 µm/s")
            && e.contains("max_speed_um_s = 20")
            && e.contains("dwell ≥ 5.000e-3 s"),
        "{e}"
    );
    // the pixels lie inside x ≤ 37.5 µm (the travel), the ramps and margins do not
    let edge = Plan::grid(
        "scan_xy",
        Sweep::new("scan_xy", Axis::X, 36.5, 37.5, 11, "nx").unwrap(),
        Sweep::new("scan_xy", Axis::Y, 0.0, 0.5, 3, "ny").unwrap(),
        vec![],
        1e-3,
        false,
        false,
    )
    .unwrap();
    let e = r.go(&mut inst, &edge, true, None).unwrap_err().to_string();
    assert!(
        e.contains("the wave of row 1 (end, ramps and margins included) leaves the soft limits")
            && e.contains("x ≤ 37.5"),
        "{e}"
    );
    assert_eq!(inst.stage.position().unwrap(), before);
}
