//! Device truth: where our device models and the vendors' documents could
//! disagree, the drivers and the emulators follow the documents (docs/hardware.md, "Device
//! truth"), and these tests hold them to it on the project's emulators:
//!
//! 1. PI: `#5` reports the trajectory; on target is `ONT?` (the settling window for the
//!    settling time, E-727 manual). A move whose `ONT?` stays 0 after `#5` = 0 is waited
//!    for, then the stage is stopped at the timeout.
//! 2. Thorlabs KPZ101: a gauge not zeroed is reported at connect and in the scan metadata;
//!    zeroing (`MGMSG_PZ_SET_ZERO`, the "zeroed" status bit) removes its offset.
//! 3. Red Pitaya: decimated samples dated at the middle of their averaging window, the sample
//!    at TPOS the last before the trigger: a snake raster of a bead gives the same position
//!    in both sweep directions (0.2 nm).
//! 4. A snake raster on PI's wave generator loads its two waves once and switches tables
//!    with `WSL`.

use bfpscope::acquire::raster::RasterOptions;
use bfpscope::acquire::run_raster;
use bfpscope::acquire::{
    run_plan, Axis, Ended, Plan, ScanEnv, ScanError, ScanRun, SoftLimits, Sweep,
};
use bfpscope::config::connect::{connect, connect_emulated_redpitaya, EmulatedStageLink};
use bfpscope::config::Config;
use bfpscope::data::Scan;
use bfpscope::instrument::emulator::{
    shared_position, standin_bead, start_kpa101_emulator, start_kpz101_emulator, start_pair,
    Emulator, KpaEmulatorConfig, KpzEmulatorConfig, QpdEmulatorConfig, StageEmulatorConfig,
};
use bfpscope::instrument::gcs::{GcsOptions, GcsStage};
use bfpscope::instrument::sim::scene::{Bead, Scene};
use bfpscope::instrument::sim::{SimConfig, SimCore};
use bfpscope::instrument::{DeviceError, Instrument, Stage};
use bfpscope::optics::params::Optics;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

fn no_sim(_: &Config) -> anyhow::Result<Instrument> {
    anyhow::bail!("the simulator must not be built for a hardware config")
}

/// Run `plan` point by point; the result and the autosaved scans.
fn run(
    inst: &mut Instrument,
    plan: &Plan,
    limits: &SoftLimits,
) -> (Result<ScanRun, ScanError>, Vec<Scan>) {
    let saved = std::sync::Mutex::new(Vec::new());
    let abort = AtomicBool::new(false);
    let log = |_: &str| {};
    let save = |s: &Scan| -> Result<std::path::PathBuf, String> {
        saved.lock().unwrap().push(s.clone());
        Ok(std::path::PathBuf::from("memory"))
    };
    let env = ScanEnv::plain(limits, &abort, &log, &save);
    let r = run_plan(inst, plan, &env);
    (r, saved.into_inner().unwrap())
}

fn line_x(from: f64, to: f64, n: i64) -> Plan {
    Plan::line(
        "ascan",
        Sweep::new("ascan", Axis::X, from, to, n, "n").unwrap(),
        1e-4,
        false,
    )
    .unwrap()
}

// ---- 1. PI: settle on what `ONT?` says ----

/// An emulated E-727 (trajectory 4 ms, settling time `settling_time_s`) and a QPD.
fn pi_pair(settling_time_s: f64) -> (Emulator, Emulator) {
    let cfg = StageEmulatorConfig {
        travel: [(-50.0, 50.0), (-40.0, 60.0), (0.0, 20.0)],
        settle_s: 0.004,
        settling_time_s,
        ..StageEmulatorConfig::default()
    };
    start_pair(cfg, QpdEmulatorConfig::default(), standin_bead).unwrap()
}

fn pi_opts(on_target_ms: u64, confirm: bool) -> GcsOptions {
    GcsOptions {
        timeout: Duration::from_millis(300),
        on_target_timeout: Duration::from_millis(on_target_ms),
        poll_interval: Duration::from_millis(1),
        confirm_on_target: confirm,
        ..GcsOptions::default()
    }
}

/// The emulated E-727 ends the trajectory after 4 ms (`#5` = 0) and is on target 30 ms later
/// (settling time 0x07000901 = 0.03 s): the driver returns after `ONT?` says so, not when
/// `#5` does; trusting `#5` alone (the old rule) returns while `ONT?` still answers 0.
#[test]
fn a_move_ends_when_ont_says_so_not_when_5_does() {
    let (emu, _q) = pi_pair(0.03);
    // the first move learns that the controller answers `#5`
    let mut s = GcsStage::open(emu.path(), 115_200, pi_opts(2000, true)).unwrap();
    s.move_to([0.5, 0.0, 0.0]).unwrap();
    let t0 = Instant::now();
    let before = emu.commands().len();
    s.move_to([1.5, 0.0, 0.0]).unwrap();
    let waited = t0.elapsed();
    assert!(waited >= Duration::from_millis(34), "{waited:?}");
    let sent = emu.commands()[before..].to_vec();
    assert_eq!(s.on_target().unwrap(), [true; 3]);
    // MOV, `#5` until the trajectory is over, then `ONT? 1` (the moved axis) until on target,
    // then the `ERR?` owed for the MOV (read once the trajectory was over)
    assert_eq!(sent[0], "MOV 1 1.500000", "{sent:?}");
    let first_ont = sent
        .iter()
        .position(|c| c == "ONT? 1")
        .expect("ONT? 1 sent");
    assert!(
        sent[1..first_ont].iter().all(|c| c == "#5" || c == "ERR?"),
        "{sent:?}"
    );
    assert!(
        sent[first_ont..]
            .iter()
            .all(|c| c == "ONT? 1" || c == "ERR?"),
        "{sent:?}"
    );
    assert!(
        sent.iter().filter(|c| *c == "ONT? 1").count() > 3,
        "{sent:?}"
    );
    assert_eq!(sent.iter().filter(|c| c.starts_with("MOV")).count(), 1);

    // the rule before the device-truth work: `#5` = 0 ends the wait, the axis not yet on target
    let (emu, _q) = pi_pair(0.03);
    let mut s = GcsStage::open(emu.path(), 115_200, pi_opts(2000, false)).unwrap();
    s.move_to([0.5, 0.0, 0.0]).unwrap();
    let t0 = Instant::now();
    s.move_to([1.5, 0.0, 0.0]).unwrap();
    assert!(
        t0.elapsed() < Duration::from_millis(30),
        "{:?}",
        t0.elapsed()
    );
    assert!(!s.on_target().unwrap()[0]);
}

/// `ONT?` never turns 1 after `#5` = 0 (settling time 30 s): the scan's move is waited for up
/// to `on_target_timeout_ms`, fails naming the controller, the query and its reply, and the
/// stage then gets `STP` and nothing else.
#[test]
fn an_axis_whose_ont_stays_0_after_5_is_waited_for_and_stopped_at_the_timeout() {
    let (emu, qpd) = pi_pair(0.0);
    let text = format!(
        "[stage]\nbackend = \"gcs\"\nport = \"{}\"\ntimeout_ms = 300\non_target_timeout_ms = 250\nsettle_s = 0.0\n\n\
         [qpd]\nbackend = \"scpi\"\nport = \"{}\"\n\n[safety]\nsoft_limits = {{ x = [-1.0, 1.0] }}\nmax_step_um = 2.0\n",
        emu.path(),
        qpd.path()
    );
    let cfg = Config::from_toml_str(&text, "test.toml").unwrap();
    // poll_ms unset: the GCS default of 1 ms
    assert_eq!(cfg.stage.poll_ms(), 1);
    let mut c = connect(&cfg, no_sim).unwrap();
    c.instrument.stage.move_to([-0.2, 0.0, 0.0]).unwrap();
    emu.faults().settling_time_s = Some(30.0);
    let before = emu.commands().len();
    let t0 = Instant::now();
    let (r, saved) = run(&mut c.instrument, &line_x(-0.4, 0.4, 5), &c.limits);
    let waited = t0.elapsed();
    let r = r.unwrap();
    match &r.ended {
        Ended::Failed {
            error: DeviceError::Other { device, detail },
            stage_fault: true,
            measured: 0,
        } => {
            assert!(
                device.contains("E-727") && device.contains(emu.path()),
                "{device}"
            );
            assert!(
                detail.starts_with("not on target within 250 ms after `MOV 1 -0.400000`"),
                "{detail}"
            );
            assert!(detail.contains("(last `ONT? 1` reply: 1=0)"), "{detail}");
            assert!(
                detail.contains("`#5` reported the trajectory over"),
                "{detail}"
            );
        }
        other => panic!("{other:?}"),
    }
    assert!(waited >= Duration::from_millis(250), "{waited:?}");
    assert_eq!(saved.len(), 1);
    std::thread::sleep(Duration::from_millis(30));
    let sent = emu.commands()[before..].to_vec();
    let mov = sent.iter().position(|c| c == "MOV 1 -0.400000").unwrap();
    let ont = sent.iter().position(|c| c == "ONT? 1").unwrap();
    assert!(sent[mov + 1..ont].contains(&"#5".to_string()), "{sent:?}");
    // the end: the timeout's ERR?, then the stop and its ERR?, nothing after
    assert_eq!(&sent[sent.len() - 2..], ["STP", "ERR?"], "{sent:?}");
    assert_eq!(
        sent.iter().filter(|c| c.starts_with("MOV")).count(),
        1,
        "{sent:?}"
    );
}

// ---- 2. Thorlabs KPZ101: zero the gauge ----

struct Kit {
    cubes: Vec<Emulator>,
    kpa: Emulator,
    pos: bfpscope::instrument::emulator::SharedPosition,
}

/// Three cubes whose gauges read `offset` µm high until zeroed (zeroing takes `zero_s`).
fn kit(offset: f64, zero_s: f64) -> Kit {
    let pos = shared_position([10.0, 10.0, 10.0]);
    let cubes = (0..3)
        .map(|axis| {
            start_kpz101_emulator(
                KpzEmulatorConfig {
                    serial: 29_000_001 + axis as u32,
                    axis,
                    travel_um: 20.0,
                    gauge_offset_um: offset,
                    zero_s,
                    ..KpzEmulatorConfig::default()
                },
                pos.clone(),
            )
            .unwrap()
        })
        .collect();
    let kpa = start_kpa101_emulator(KpaEmulatorConfig::default(), pos.clone(), |p: [f64; 3]| {
        standin_bead([p[0] - 10.0, p[1] - 10.0, p[2] - 10.0])
    })
    .unwrap();
    Kit { cubes, kpa, pos }
}

/// (The reply timeouts are 2 s: the cubes' emulators answer from threads on wall-clock time, and
/// with the machine's two cores busy a reply once missed 300 ms. No test here waits on one.)
fn kpz_config(k: &Kit, extra: &str) -> Config {
    let text = format!(
        "[stage]\nbackend = \"kpz101\"\nports = {{ x = \"{}\", y = \"{}\", z = \"{}\" }}\ntimeout_ms = 2000\n\
         settle_s = 0.0\ntolerance_um = 0.001\n{extra}\n\n[qpd]\nbackend = \"kpa101\"\nport = \"{}\"\ntimeout_ms = 2000\n\n\
         [safety]\nmax_step_um = 2.0\n",
        k.cubes[0].path(),
        k.cubes[1].path(),
        k.cubes[2].path(),
        k.kpa.path()
    );
    Config::from_toml_str(&text, "test.toml").unwrap()
}

#[test]
fn a_kpz101_gauge_not_zeroed_is_reported_and_zeroing_removes_its_offset() {
    let k = kit(0.5, 0.02);
    let cfg = kpz_config(&k, "");
    // poll_ms unset: the KPZ101 default of 10 ms, not the GCS one
    assert_eq!(cfg.stage.poll_ms(), 10);
    let mut c = connect(&cfg, no_sim).unwrap();
    // the status was asked at connect; the warning names the cubes and the remedy
    assert!(k.cubes[0]
        .commands()
        .contains(&"0x0660 MGMSG_PZ_REQ_PZSTATUSUPDATE (01, 00)".to_string()));
    let d = &c.instrument.description;
    assert_eq!(
        d["stage"]["gauge_zeroed"],
        serde_json::json!({"x": false, "y": false, "z": false})
    );
    assert_eq!(d["stage"]["cubes"][1]["gauge_zeroed_at_connect"], false);
    let w = d["warnings"][0].as_str().unwrap();
    assert!(
        w.contains("Thorlabs KPZ101") && w.contains("the strain gauge of x, y, z is not zeroed"),
        "{w}"
    );
    assert!(
        w.contains("zero_gauge()") && w.contains("zero_at_connect"),
        "{w}"
    );
    // not zeroed: the loop holds the gauge's reading on the demand, the actuator 0.5 µm short
    c.instrument.stage.move_to([11.0, 10.0, 10.0]).unwrap();
    std::thread::sleep(Duration::from_millis(10));
    let actual = k.pos.lock().unwrap()[0];
    assert!((actual - 10.5).abs() < 2e-3, "{actual}");
    assert!((c.instrument.stage.position().unwrap()[0] - 11.0).abs() < 2e-3);
    // a scan records the state
    let (r, _) = run(&mut c.instrument, &line_x(10.8, 11.2, 3), &c.limits);
    assert_eq!(r.as_ref().unwrap().ended, Ended::Complete);
    assert_eq!(
        r.unwrap().scan.meta["instrument"]["stage"]["gauge_zeroed"]["y"],
        false
    );

    // zeroing: MGMSG_PZ_SET_ZERO to each cube, the status polled until "zeroed"
    let z = c
        .instrument
        .stage
        .gauge()
        .expect("KPZ101 cubes offer a gauge zero")
        .zero_gauge()
        .unwrap();
    bfpscope::config::connect::record_gauge(&mut c.instrument);
    assert_eq!(z, [true; 3]);
    for cube in &k.cubes {
        let log = cube.commands();
        let i = log
            .iter()
            .position(|m| m == "0x0658 MGMSG_PZ_SET_ZERO (01, 00)")
            .expect("SET_ZERO");
        assert_eq!(log[i + 1], "0x0660 MGMSG_PZ_REQ_PZSTATUSUPDATE (01, 00)");
    }
    let d = &c.instrument.description;
    assert_eq!(
        d["stage"]["gauge_zeroed"],
        serde_json::json!({"x": true, "y": true, "z": true})
    );
    assert!(d.get("warnings").is_none(), "{d}");
    // the actuators sit at their zero, and a move now puts them where the reading says
    assert!(k.pos.lock().unwrap()[0].abs() < 2e-3);
    let (r, _) = run(&mut c.instrument, &line_x(0.5, 1.5, 3), &c.limits);
    let r = r.unwrap();
    assert_eq!(r.ended, Ended::Complete);
    assert_eq!(
        r.scan.meta["instrument"]["stage"]["gauge_zeroed"]["x"],
        true
    );
    c.instrument.stage.move_to([11.0, 10.0, 10.0]).unwrap();
    std::thread::sleep(Duration::from_millis(10));
    let actual = k.pos.lock().unwrap()[0];
    assert!((actual - 11.0).abs() < 2e-3, "{actual}");
}

#[test]
fn zero_at_connect_zeroes_before_the_loop_closes_and_a_slow_zeroing_is_a_fault_that_holds() {
    let k = kit(0.5, 0.02);
    let c = connect(&kpz_config(&k, "zero_at_connect = true"), no_sim).unwrap();
    assert_eq!(
        c.instrument.description["stage"]["gauge_zeroed"],
        serde_json::json!({"x": true, "y": true, "z": true})
    );
    assert!(c.instrument.description.get("warnings").is_none());
    let log = k.cubes[2].commands();
    let zero = log
        .iter()
        .position(|m| m == "0x0658 MGMSG_PZ_SET_ZERO (01, 00)")
        .unwrap();
    let closed = log
        .iter()
        .position(|m| m == "0x0640 MGMSG_PZ_SET_POSCONTROLMODE (01, 02)")
        .unwrap();
    assert!(zero < closed, "{log:?}");
    drop(c);

    // zeroing takes 10 s, the timeout is 150 ms: the error names the cube, the message and the
    // status bits (zeroing set, zeroed clear); the cube is told to hold where it is
    let k = kit(0.5, 10.0);
    let e = connect(
        &kpz_config(&k, "zero_at_connect = true\nzero_timeout_ms = 150"),
        no_sim,
    )
    .err()
    .expect("refused")
    .to_string();
    std::thread::sleep(Duration::from_millis(50));
    assert!(e.contains("Thorlabs KPZ101 #29000001 (x)"), "{e}");
    assert!(
        e.contains("strain gauge not zeroed within 150 ms after `0x0658 MGMSG_PZ_SET_ZERO (01, 00)`: last status bits 0x00000121 (zeroing 1, zeroed 0)"),
        "{e}"
    );
    let log = k.cubes[0].commands();
    let zero = log
        .iter()
        .position(|m| m == "0x0658 MGMSG_PZ_SET_ZERO (01, 00)")
        .unwrap();
    assert!(
        log[zero..]
            .iter()
            .any(|m| m.starts_with("0x0646 MGMSG_PZ_SET_OUTPUTPOS")),
        "{log:?}"
    );
    // the other cubes were not touched: no zeroing sent to y
    assert!(!k.cubes[1].commands().iter().any(|m| m.contains("SET_ZERO")));
}

// ---- 3 and 4. Red Pitaya dating, snake rasters with two wave tables ----

/// x where Sx crosses zero on `row` (linear between the two pixels around it), µm.
fn zero_crossing(sx: &[f64], xs: &[f64]) -> Option<f64> {
    let c = xs.len() / 2;
    (c - 4..c + 4).find_map(|i| {
        let (a, b) = (sx[i], sx[i + 1]);
        (a.signum() != b.signum() && a != b).then(|| xs[i] + (xs[i + 1] - xs[i]) * a / (a - b))
    })
}

/// A snake raster of a 110 nm bead at 50 µm/s (25 nm pixels, 0.5 ms dwell, 40 samples per
/// pixel: the board at decimation 1024, 8.2 µs per sample) through the real drivers and the
/// emulators: the bead's x from the forward rows and from the backward rows agree to 0.2 nm.
/// Dating each sample at the start of its window (the driver before the device-truth work) would shift the
/// two directions apart by 2·v·dt = 0.8 nm. And the snake loads its two waves once: every
/// later line is one `WSL` switching tables.
#[test]
fn bead_positions_agree_in_both_raster_directions_and_the_snake_switches_tables() {
    let bead_x = 0.013;
    let mut scene = Scene::default();
    scene
        .add_bead(Bead {
            pos: [bead_x, 0.0, 0.0],
            d_nm: 110.0,
            n: 1.572,
        })
        .unwrap();
    let core = SimCore::new(&Optics::default(), &scene, SimConfig::default()).unwrap();
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
    let (nx, ny) = (33i64, 32i64);
    let plan = Plan::grid(
        "scan_xy",
        Sweep::new("scan_xy", Axis::X, -0.4, 0.4, nx, "nx").unwrap(),
        Sweep::new("scan_xy", Axis::Y, -0.08, 0.08, ny, "ny").unwrap(),
        vec![],
        0.5e-3,
        false,
        true,
    )
    .unwrap();
    let limits: SoftLimits = e.connected.limits;
    let abort = AtomicBool::new(false);
    let log = |_: &str| {};
    let save = |_: &Scan| -> Result<std::path::PathBuf, String> { Ok("memory".into()) };
    let env = ScanEnv::plain(&limits, &abort, &log, &save);
    let before = e.stage.commands().len();
    let r = run_raster(
        &mut e.connected.instrument,
        &plan,
        &RasterOptions {
            samples_per_pixel: 40,
        },
        &env,
    )
    .unwrap();
    assert_eq!(r.ended, Ended::Complete);
    let dec = r.scan.meta["last_acquisition"]["decimation"].as_u64();
    assert_eq!(dec, Some(1024), "{}", r.scan.meta);
    let xs: Vec<f64> = r.scan.sx.x.clone();
    let (mut fwd, mut back) = (Vec::new(), Vec::new());
    for row in 0..ny as usize {
        let sx: Vec<f64> = (0..nx as usize).map(|j| r.scan.sx.data[[row, j]]).collect();
        let x0 = zero_crossing(&sx, &xs).unwrap_or_else(|| panic!("row {row}: {sx:?}"));
        if row % 2 == 0 {
            fwd.push(x0)
        } else {
            back.push(x0)
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (f, b) = (mean(&fwd), mean(&back));
    eprintln!(
        "forward {f} µm, backward {b} µm: {:.3} nm apart",
        (f - b) * 1e3
    );
    assert!(
        (f - b).abs() < 0.2e-3,
        "forward {f} µm, backward {b} µm: {:.3} nm apart",
        (f - b) * 1e3
    );
    // and both near the bead (the linear interpolation of Sx between pixels errs by ~1 nm)
    assert!((f - bead_x).abs() < 3e-3, "{f}");

    // the stage: two WAV (forward into table 1, back into 2), one full configuration, then
    // one `WSL` per line alternating the tables
    let sent = e.stage.commands()[before..].to_vec();
    let wav: Vec<&String> = sent.iter().filter(|c| c.starts_with("WAV ")).collect();
    assert_eq!(wav.len(), 2, "{wav:?}");
    assert!(
        wav[0].starts_with("WAV 1 X LIN") && wav[1].starts_with("WAV 2 X LIN"),
        "{wav:?}"
    );
    assert_eq!(sent.iter().filter(|c| c.starts_with("DRC ")).count(), 1);
    assert_eq!(sent.iter().filter(|c| c.starts_with("WGC ")).count(), 1);
    let wsl: Vec<&str> = sent
        .iter()
        .filter(|c| c.starts_with("WSL "))
        .map(|c| c.as_str())
        .collect();
    assert_eq!(wsl.len(), ny as usize, "{wsl:?}");
    for (i, w) in wsl.iter().enumerate() {
        assert_eq!(
            *w,
            if i % 2 == 0 { "WSL 1 1" } else { "WSL 1 2" },
            "{wsl:?}"
        );
    }
    assert_eq!(sent.iter().filter(|c| *c == "WGO 1 1").count(), ny as usize);
}
