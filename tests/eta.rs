//! ETAs on the real-time backends: the FIRST scan after connecting, before the
//! drivers have measured anything, must promise within 20 % of what it takes, on the emulators
//! with their modelled links (`bfpscope emulate`'s default: 115200 baud, 1 ms latency). The
//! ETA comes from the device-side cost models (link bytes at the baud rate, the latency measured
//! on the connect's replies, the turnarounds of each step), and each model is checked against
//! the scan's own `meta.time.phases`, so a good total cannot hide two compensating errors.

use bfpscope::acquire::raster::RasterOptions;
use bfpscope::acquire::strategy::line::LineStrategy;
use bfpscope::acquire::{run, run_plan, Axis, Plan, ScanEnv, ScanRun, SoftLimits, Sweep};
use bfpscope::config::connect::connect;
use bfpscope::config::Config;
use bfpscope::data::Scan;
use bfpscope::instrument::emulator::{
    shared_position, standin_bead, start_kpa101_emulator, start_kpz101_stage_on, start_pair,
    start_redpitaya_emulator, start_stage_emulator, KpaEmulatorConfig, LinkModel,
    QpdEmulatorConfig, RedPitayaEmulatorConfig, StageEmulatorConfig, StagePath,
};
use bfpscope::instrument::Instrument;
use std::sync::atomic::AtomicBool;

fn run_points(inst: &mut Instrument, plan: &Plan, limits: &SoftLimits) -> ScanRun {
    let abort = AtomicBool::new(false);
    let log = |s: &str| eprintln!("{s}");
    let save = |_: &Scan| -> Result<std::path::PathBuf, String> { Ok("memory".into()) };
    let env = ScanEnv::plain(limits, &abort, &log, &save);
    run_plan(inst, plan, &env).expect("the scan runs")
}

fn run_raster(inst: &mut Instrument, plan: &Plan, limits: &SoftLimits) -> ScanRun {
    let abort = AtomicBool::new(false);
    let log = |s: &str| eprintln!("{s}");
    let save = |_: &Scan| -> Result<std::path::PathBuf, String> { Ok("memory".into()) };
    let env = ScanEnv::plain(limits, &abort, &log, &save);
    let mut st = LineStrategy::new(RasterOptions::default());
    run(inst, plan, &mut st, &env).expect("the raster runs")
}

fn grid(c: f64, n: i64, dwell_s: f64) -> Plan {
    Plan::grid(
        "scan_xy",
        Sweep::new("scan_xy", Axis::X, c - 0.5, c + 0.5, n, "nx").unwrap(),
        Sweep::new("scan_xy", Axis::Y, c - 0.5, c + 0.5, n, "ny").unwrap(),
        vec![],
        dwell_s,
        false,
        false,
    )
    .unwrap()
}

/// |a/b − 1| ≤ tol, with the numbers in the message.
fn within(a: f64, b: f64, tol: f64, what: &str) {
    assert!(
        (a / b - 1.0).abs() <= tol,
        "{what}: predicted {a:.4} vs measured {b:.4} ({:+.0} %)",
        100.0 * (a / b - 1.0)
    );
}

/// PI GCS stage + SCPI QPD (`bfpscope emulate pair`), point by point.
#[test]
fn the_first_point_scan_on_the_gcs_scpi_pair_keeps_its_eta() {
    let link = LinkModel::USB_SERIAL_115200;
    let stage = StageEmulatorConfig {
        travel: [(-2.0, 2.0), (-2.0, 2.0), (-1.0, 1.0)],
        link,
        ..Default::default()
    };
    let qpd = QpdEmulatorConfig {
        link,
        ..Default::default()
    };
    let (se, qe) = start_pair(stage, qpd, standin_bead).unwrap();
    let text = format!(
        "[stage]\nbackend = \"gcs\"\nport = \"{}\"\nsettle_s = 0.005\n[qpd]\nbackend = \"scpi\"\nport = \"{}\"\n",
        se.path(),
        qe.path()
    );
    let cfg = Config::from_toml_str(&text, "test.toml").unwrap();
    let mut c = connect(&cfg, |_| panic!("no simulator")).unwrap();
    let limits = c.limits;
    // the drivers' models before anything was measured
    let move_prior = c.instrument.stage.move_time_s();
    let qpd_prior = c.instrument.qpd.overhead_s();
    assert!(
        move_prior > 0.0 && qpd_prior > 0.0,
        "{move_prior} {qpd_prior}"
    );
    // 12 × 12 points, ~3 s
    let r = run_points(&mut c.instrument, &grid(0.0, 12, 1e-3), &limits);
    let t = &r.scan.meta["time"];
    let (eta, wall) = (t["eta_s"].as_f64().unwrap(), t["wall_s"].as_f64().unwrap());
    let p = &t["phases"];
    eprintln!(
        "ETA {eta:.3} s, measured {wall:.3} s; move prior {:.2} ms, QPD prior {:.2} ms; phases {p}",
        1e3 * move_prior,
        1e3 * qpd_prior
    );
    // where the time went, model by model (the machine is loaded: 30 % per phase)
    within(
        1e3 * move_prior,
        p["move_ms"].as_f64().unwrap(),
        0.3,
        "move per point, ms",
    );
    within(
        1e3 * qpd_prior,
        p["qpd_beyond_dwell_ms"].as_f64().unwrap(),
        0.3,
        "QPD read beyond the dwell, ms",
    );
    within(eta, wall, 0.2, "the first scan's ETA, s");
}

/// Three Thorlabs KPZ101 cubes + a KPA101 position aligner (`bfpscope emulate thorlabs`: USB
/// serial at APT's 115200 baud, 1 ms latency), point by point, at the backends' default poll
/// interval (10 ms for the cubes).
#[test]
fn the_first_point_scan_on_the_thorlabs_cubes_keeps_its_eta_and_shows_its_links() {
    let pos = shared_position([10.0, 10.0, 10.0]);
    let link = LinkModel::USB_SERIAL_115200;
    let cubes = start_kpz101_stage_on([20.0; 3], pos.clone(), link).unwrap();
    let kpa = start_kpa101_emulator(
        KpaEmulatorConfig {
            link,
            ..Default::default()
        },
        pos,
        standin_bead,
    )
    .unwrap();
    let text = format!(
        "[stage]\nbackend = \"kpz101\"\nports = {{ x = \"{}\", y = \"{}\", z = \"{}\" }}\nsettle_s = 0.005\n\
         [qpd]\nbackend = \"kpa101\"\nport = \"{}\"\n",
        cubes[0].path(),
        cubes[1].path(),
        cubes[2].path(),
        kpa.path()
    );
    let cfg = Config::from_toml_str(&text, "test.toml").unwrap();
    let mut c = connect(&cfg, |_| panic!("no simulator")).unwrap();
    let limits = c.limits;
    let move_prior = c.instrument.stage.move_time_s();
    assert!(move_prior > 0.0, "{move_prior}");
    // 10 × 10 points around the middle of the travel, ~2 s
    let r = run_points(&mut c.instrument, &grid(10.0, 10, 1e-3), &limits);
    let t = &r.scan.meta["time"];
    let (eta, wall) = (t["eta_s"].as_f64().unwrap(), t["wall_s"].as_f64().unwrap());
    let p = &t["phases"];
    eprintln!(
        "ETA {eta:.3} s, measured {wall:.3} s; move prior {:.2} ms; phases {p}",
        1e3 * move_prior
    );
    // the timing line's breakdowns: every message the cubes and the aligner exchanged
    let stage = p["stage_link"].as_object().unwrap();
    assert!(
        stage.contains_key("MGMSG_PZ_SET_OUTPUTPOS")
            && stage.contains_key("MGMSG_PZ_REQ_OUTPUTPOS"),
        "{p}"
    );
    assert_eq!(
        stage["MGMSG_PZ_REQ_OUTPUTPOS"]["bytes_per_point"]
            .as_f64()
            .unwrap()
            / stage["MGMSG_PZ_REQ_OUTPUTPOS"]["per_point"]
                .as_f64()
                .unwrap(),
        16.0,
        "6 bytes out, 10 back"
    );
    let qpd = p["qpd_link"].as_object().unwrap();
    assert_eq!(
        qpd["MGMSG_QUAD_REQ_PARAMS"]["bytes_per_point"], 24.0,
        "6 out, 6 + 12 back"
    );
    assert!(p["link_bytes_per_point"].as_f64().unwrap() > 24.0, "{p}");
    within(
        1e3 * move_prior,
        p["move_ms"].as_f64().unwrap(),
        0.3,
        "move per point, ms",
    );
    within(eta, wall, 0.2, "the first scan's ETA, s");
}

/// A PI GCS stage (wave generator, data recorder; 115200 baud, 1 ms) whose OUT1 triggers a Red
/// Pitaya (`bfpscope emulate redpitaya`), a hardware-timed raster. The board samples a cheap
/// stand-in signal: the emulator's own rendering of a simulated scene (`emulate redpitaya`
/// renders every sample of the path with the simulator, ~0.4 s a line in a debug build) is the
/// emulator's work, not the board's, and no device model can know it.
#[test]
fn the_first_raster_on_the_gcs_red_pitaya_pair_keeps_its_eta() {
    let pos = shared_position([0.0; 3]);
    let path = StagePath::new();
    let (rp, ext) = start_redpitaya_emulator(
        RedPitayaEmulatorConfig {
            path: Some(path.clone()),
            ..RedPitayaEmulatorConfig::default()
        },
        pos.clone(),
        standin_bead,
        "127.0.0.1:0",
    )
    .unwrap();
    let mut stage = StageEmulatorConfig {
        travel: [(-5.0, 5.0), (-5.0, 5.0), (-1.0, 1.0)],
        link: LinkModel::USB_SERIAL_115200,
        ..Default::default()
    };
    stage.wave.trigger_out[0] = Some(ext);
    stage.wave.path = Some(path);
    let se = start_stage_emulator(stage, pos).unwrap();
    let hp = rp.path().trim_start_matches("tcp://").to_string();
    let (host, port) = hp.rsplit_once(':').unwrap();
    let text = format!(
        "[stage]\nbackend = \"gcs\"\nport = \"{}\"\ntrigger_line = 1\n[qpd]\nbackend = \"redpitaya\"\nhost = \"{host}\"\nport = {port}\nchannels = {{ sx = 1, sy = 2 }}\n",
        se.path()
    );
    let cfg = Config::from_toml_str(&text, "test.toml").unwrap();
    let mut c = connect(&cfg, |_| panic!("no simulator")).unwrap();
    let limits = c.limits;
    // 32 × 8, 1 ms a pixel: the recorder's readout dominates each line
    let plan = Plan::grid(
        "scan_xy",
        Sweep::new("scan_xy", Axis::X, -1.0, 1.0, 32, "nx").unwrap(),
        Sweep::new("scan_xy", Axis::Y, -1.0, 1.0, 8, "ny").unwrap(),
        vec![],
        1e-3,
        false,
        false,
    )
    .unwrap();
    let r = run_raster(&mut c.instrument, &plan, &limits);
    let t = &r.scan.meta["time"];
    let (eta, wall) = (t["eta_s"].as_f64().unwrap(), t["wall_s"].as_f64().unwrap());
    eprintln!("ETA {eta:.3} s, measured {wall:.3} s; {}", t["lines"]);
    within(eta, wall, 0.2, "the first raster's ETA, s");
}
