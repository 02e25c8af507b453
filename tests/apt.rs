//! Thorlabs APT devices (KPA101 position aligner as the QPD, three KPZ101 piezo cubes as the
//! stage) driven through their drivers against emulators on pseudo-terminals: bytes on the
//! wire, decoded numbers, faults, and a scan through the engine.

use crate::support::cleanup;

use bfpscope::acquire::{run_plan, Axis, Ended, Plan, ScanEnv, ScanError, SoftLimits, Sweep};
use bfpscope::config::connect::{connect, Connected};
use bfpscope::config::Config;
use bfpscope::data::{Scan, ScanStatus};
use bfpscope::instrument::emulator::{
    shared_position, standin_bead, start_kpa101_emulator, start_kpz101_stage, Emulator,
    KpaEmulatorConfig, SignalSource, UNKNOWN_ID,
};
use bfpscope::instrument::thorlabs::{id, AptLink, Message};
use bfpscope::instrument::{DeviceError, Instrument};
use std::sync::atomic::AtomicBool;
use std::time::Duration;

/// The stand-in bead sits here (µm, inside the cubes' 0–20 µm travel).
const BEAD: [f64; 3] = [10.0, 10.0, 10.0];

fn bead(p: [f64; 3]) -> [f64; 3] {
    standin_bead([p[0] - BEAD[0], p[1] - BEAD[1], p[2] - BEAD[2]])
}

struct Kit {
    cubes: [Emulator; 3],
    kpa: Emulator,
}

fn kit(source: impl SignalSource) -> Kit {
    let pos = shared_position([10.0, 10.0, 10.0]);
    let cubes = start_kpz101_stage([20.0; 3], pos.clone()).unwrap();
    let kpa = start_kpa101_emulator(KpaEmulatorConfig::default(), pos, source).unwrap();
    Kit { cubes, kpa }
}

fn config_text(k: &Kit, qpd_extra: &str) -> String {
    format!(
        "[stage]\nbackend = \"kpz101\"\nports = {{ x = \"{}\", y = \"{}\", z = \"{}\" }}\ntimeout_ms = 300\npoll_ms = 1\n\
         settle_s = 0.0\ntolerance_um = 0.001\n\n[qpd]\nbackend = \"kpa101\"\nport = \"{}\"\ntimeout_ms = 300\n{qpd_extra}\n\n[safety]\nmax_step_um = 2.0\n",
        k.cubes[0].path(),
        k.cubes[1].path(),
        k.cubes[2].path(),
        k.kpa.path()
    )
}

fn no_sim(_: &Config) -> anyhow::Result<Instrument> {
    anyhow::bail!("not simulated")
}

fn connected(k: &Kit, qpd_extra: &str) -> Connected {
    let cfg = Config::from_toml_str(&config_text(k, qpd_extra), "test.toml").unwrap();
    connect(&cfg, no_sim).unwrap()
}

#[test]
fn connect_sends_the_documented_messages_and_reads_travel() {
    let k = kit(bead);
    let mut c = connected(&k, "");
    // every cube: read-only identification first (the gauge's zero state with the status
    // update), then (after the limits fit) closed loop,
    // demand = position read (10 µm of 20 → 16384 counts of 32767 = 0x4000), channel enable
    let log = k.cubes[0].commands();
    assert_eq!(
        log,
        [
            "0x0018 MGMSG_HW_NO_FLASH_PROGRAMMING (00, 00)",
            "0x0012 MGMSG_HW_STOP_UPDATEMSGS (00, 00)",
            "0x0005 MGMSG_HW_REQ_INFO (00, 00)",
            "0x0211 MGMSG_MOD_REQ_CHANENABLESTATE (01, 00)",
            "0x0641 MGMSG_PZ_REQ_POSCONTROLMODE (01, 00)",
            "0x0660 MGMSG_PZ_REQ_PZSTATUSUPDATE (01, 00)",
            "0x0650 MGMSG_PZ_REQ_MAXTRAVEL (01, 00)",
            "0x0647 MGMSG_PZ_REQ_OUTPUTPOS (01, 00)",
            "0x0647 MGMSG_PZ_REQ_OUTPUTPOS (01, 00)",
            "0x0640 MGMSG_PZ_SET_POSCONTROLMODE (01, 02)",
            "0x0646 MGMSG_PZ_SET_OUTPUTPOS [01 00 00 40]",
            "0x0210 MGMSG_MOD_SET_CHANENABLESTATE (01, 01)",
            "0x0641 MGMSG_PZ_REQ_POSCONTROLMODE (01, 00)",
            "0x0211 MGMSG_MOD_REQ_CHANENABLESTATE (01, 00)",
        ]
    );
    // the aligner: monitor mode (sub-message 7, mode 1) set and read back, then readings
    let qlog = k.kpa.commands();
    assert_eq!(qlog[3], "0x0870 MGMSG_QUAD_SET_PARAMS [07 00 01 00]");
    assert_eq!(qlog[4], "0x0871 MGMSG_QUAD_REQ_PARAMS (07, 00)");
    assert!(qlog[5..]
        .iter()
        .all(|m| m == "0x0871 MGMSG_QUAD_REQ_PARAMS (03, 00)"));
    let d = &c.instrument.description;
    assert_eq!(d["stage"]["cubes"][2]["device"]["serial"], 29_000_003);
    assert_eq!(d["stage"]["cubes"][0]["travel_um"], 20.0);
    assert_eq!(d["stage"]["cubes"][0]["mode_at_connect"], 1);
    assert_eq!(d["qpd"]["device"]["model"], "KPA101");
    assert_eq!(c.instrument.stage.travel_range().unwrap(), [(0.0, 20.0); 3]);
    let p = c.instrument.stage.position().unwrap();
    assert!(p.iter().all(|v| (v - 10.0).abs() < 1e-3), "{p:?}");
    assert!(c
        .instrument
        .stage
        .name()
        .contains("x #29000001 on /dev/pts/"));
}

#[test]
fn a_move_is_one_set_outputpos_per_changed_axis_with_le_counts() {
    let k = kit(bead);
    let mut c = connected(&k, "");
    let before: Vec<usize> = k.cubes.iter().map(|e| e.commands().len()).collect();
    // x to 5 µm: 5/20 · 32767 = 8191.75 → 8192 = 0x2000; y and z unchanged → not sent
    let t = c.instrument.stage.target().unwrap();
    c.instrument.stage.move_to([5.0, t[1], t[2]]).unwrap();
    let x = &k.cubes[0].commands()[before[0]..];
    assert_eq!(x[0], "0x0646 MGMSG_PZ_SET_OUTPUTPOS [01 00 00 20]");
    assert!(x[1..]
        .iter()
        .all(|m| m == "0x0647 MGMSG_PZ_REQ_OUTPUTPOS (01, 00)"));
    assert!(k.cubes[1].commands()[before[1]..].is_empty());
    assert!(k.cubes[2].commands()[before[2]..].is_empty());
    let p = k.kpa.position();
    assert!((p[0] - 8192.0 / 32767.0 * 20.0).abs() < 1e-9, "{p:?}");
    let m = c.instrument.stage.position().unwrap();
    assert!((m[0] - 5.0).abs() < 1e-3, "{m:?}");
}

#[test]
fn kpa101_readings_decode_to_normalised_signals() {
    // constant signal: Sum = 5 V · (1 + 0.2) = 6 V, XDiff = 0.1 · 6 = 0.6 V, YDiff = −0.3 V
    let k = kit(|_| [0.1, -0.05, 0.2]);
    let mut c = connected(&k, "");
    let r = c.instrument.qpd.read(4).unwrap();
    assert_eq!(r.n, 4);
    // quantisation: 10 V / 32767 per count of the differences
    assert!((r.sx - 0.1).abs() < 1e-4, "{r}");
    assert!((r.sy + 0.05).abs() < 1e-4, "{r}");
    assert!((r.sz - 6.0).abs() < 2e-4, "{r}");
    assert_eq!((r.sx_std, r.sz_std), (0.0, 0.0));
    assert_eq!(
        k.kpa.commands().last().unwrap(),
        "0x0871 MGMSG_QUAD_REQ_PARAMS (03, 00)"
    );
}

#[test]
fn kpa101_disputed_conventions_are_settable() {
    let k = kit(|_| [0.1, -0.05, 0.2]);
    // pylablib's conventions: X inverted, Sum at 20 V / 32767 per count
    let mut c = connected(&k, "x_sign = -1\nsum_scale = 6.103888e-4");
    let r = c.instrument.qpd.read(1).unwrap();
    // Sum: 6 V sent as 39321 counts; read at 20/32767 V per count: 24.0 V (4× the document)
    assert!((r.sz - 39321.0 * 6.103888e-4).abs() < 1e-6, "{r}");
    assert!((r.sx + 0.1 / 4.0).abs() < 1e-4, "{r}");
    drop(c);
    // the Sum read as signed: 39321 counts are negative → refused, naming the reading
    let mut c = connected(&k, "signed = true");
    match c.instrument.qpd.read(1) {
        Err(DeviceError::Other { device, detail }) => {
            assert!(
                device.starts_with("Thorlabs KPA101 #69000001 on /dev/pts/"),
                "{device}"
            );
            assert!(
                detail.contains("MGMSG_QUAD_REQ_PARAMS (03, 00)"),
                "{detail}"
            );
            assert!(detail.contains("no light on the detector"), "{detail}");
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn bad_kpa_and_kpz_keys_name_key_value_and_allowed_values() {
    let k = kit(bead);
    let text = config_text(&k, "x_sign = 2");
    let e = Config::from_toml_str(&text, "test.toml").unwrap_err();
    assert_eq!(e.key, "qpd.x_sign");
    assert!(e.message.contains("2: allowed values are 1 and -1"), "{e}");
    let text = config_text(&k, "").replace("poll_ms = 1", "poll_ms = 1\nfull_scale = 4096");
    let e = Config::from_toml_str(&text, "test.toml").unwrap_err();
    assert_eq!(e.key, "stage.full_scale");
    assert!(e.message.contains("4096: allowed values are 32767"), "{e}");
    let text = config_text(&k, "").replace(k.cubes[1].path(), k.cubes[0].path());
    let e = Config::from_toml_str(&text, "test.toml").unwrap_err();
    assert_eq!(e.key, "stage.ports.y");
    let text = config_text(&k, "").replace("backend = \"kpa101\"", "backend = \"kpz101\"");
    let e = Config::from_toml_str(&text, "test.toml").unwrap_err();
    assert_eq!(e.key, "qpd.backend");
    assert!(
        e.message
            .contains("allowed for a QPD: \"sim\", \"scpi\", \"kpa101\""),
        "{e}"
    );
}

#[test]
fn unknown_message_from_the_device_is_skipped() {
    let k = kit(|_| [0.1, -0.05, 0.2]);
    let mut c = connected(&k, "");
    k.kpa.faults().apt_unsolicited = 3;
    let r = c.instrument.qpd.read(3).unwrap();
    assert!((r.sx - 0.1).abs() < 1e-4, "{r}");
    assert_eq!(k.kpa.faults().apt_unsolicited, 0);
}

#[test]
fn unknown_message_to_the_device_is_ignored_like_a_real_unit() {
    let k = kit(bead);
    let io = bfpscope::instrument::link::open_serial(
        "test",
        k.cubes[0].path(),
        115_200,
        Duration::from_millis(200),
    )
    .unwrap();
    let mut link = AptLink::new(io, "KPZ101 test", Duration::from_millis(200));
    let unknown = Message::short(UNKNOWN_ID, 0x01, 0x00);
    match link.request(&unknown, UNKNOWN_ID + 1) {
        Err(DeviceError::Timeout {
            device,
            command,
            timeout_ms,
        }) => {
            assert_eq!(device, "KPZ101 test");
            assert_eq!(command, "0x0999 unknown message (01, 00)");
            assert_eq!(timeout_ms, 200);
        }
        other => panic!("{other:?}"),
    }
    // the unit is not confused: the next request is answered (20 µm travel = 200 × 100 nm)
    let r = link
        .request(
            &Message::short(id::PZ_REQ_MAXTRAVEL, 0x01, 0x00),
            id::PZ_GET_MAXTRAVEL,
        )
        .unwrap();
    assert_eq!(r.bytes(), [0x01, 0x00, 200, 0x00]);
    assert_eq!(
        k.cubes[0].commands(),
        [
            "0x0999 unknown message (01, 00)",
            "0x0650 MGMSG_PZ_REQ_MAXTRAVEL (01, 00)"
        ]
    );
}

#[test]
fn silent_aligner_times_out_naming_device_and_message() {
    let k = kit(bead);
    let mut c = connected(&k, "");
    k.kpa.faults().silent = true;
    match c.instrument.qpd.read(2) {
        Err(DeviceError::Timeout {
            device,
            command,
            timeout_ms,
        }) => {
            assert!(
                device.starts_with("Thorlabs KPA101 #69000001 on /dev/pts/"),
                "{device}"
            );
            assert_eq!(command, "0x0871 MGMSG_QUAD_REQ_PARAMS (03, 00)");
            assert_eq!(timeout_ms, 300);
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn garbled_packet_is_garbled_with_the_bytes() {
    let k = kit(bead);
    let mut c = connected(&k, "");
    k.kpa.faults().garble_replies = 1;
    match c.instrument.qpd.read(1) {
        Err(DeviceError::Garbled { command, reply, .. }) => {
            assert_eq!(command, "0x0871 MGMSG_QUAD_REQ_PARAMS (03, 00)");
            // GET_PARAMS header with destination and source replaced by 0xff
            assert!(reply.starts_with("[72 08 0c 00 ff ff"), "{reply}");
            assert!(reply.contains("destination 0xff / source 0xff"), "{reply}");
        }
        other => panic!("{other:?}"),
    }
    // the next reading is fine again
    assert!(c.instrument.qpd.read(1).is_ok());
}

#[test]
fn device_error_report_is_a_controller_error_with_its_text() {
    let k = kit(bead);
    let mut c = connected(&k, "");
    k.kpa.faults().error_next = Some(42);
    match c.instrument.qpd.read(1) {
        Err(DeviceError::Controller {
            command,
            code,
            message,
            ..
        }) => {
            assert_eq!(command, "0x0871 MGMSG_QUAD_REQ_PARAMS (03, 00)");
            assert_eq!(code, 42);
            assert_eq!(message, "emulated fault 42 (about message 0x0871)");
        }
        other => panic!("{other:?}"),
    }
}

fn run(
    inst: &mut Instrument,
    plan: &Plan,
    limits: &SoftLimits,
) -> (bfpscope::acquire::ScanRun, Vec<Scan>) {
    let saved = std::sync::Mutex::new(Vec::new());
    let abort = AtomicBool::new(false);
    let log = |_: &str| {};
    let save = |s: &Scan| -> Result<std::path::PathBuf, String> {
        saved.lock().unwrap().push(s.clone());
        Ok(std::path::PathBuf::from("memory"))
    };
    let env = ScanEnv::plain(limits, &abort, &log, &save);
    let r: Result<_, ScanError> = run_plan(inst, plan, &env);
    (r.unwrap(), saved.into_inner().unwrap())
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

#[test]
fn scan_through_the_engine_recovers_the_bead() {
    let k = kit(bead);
    let mut c = connected(&k, "");
    let limits = c.limits;
    let (r, saved) = run(&mut c.instrument, &line_x(9.5, 10.5, 11), &limits);
    assert_eq!(r.ended, Ended::Complete);
    assert_eq!(saved.len(), 1);
    for i in 0..11 {
        let x = 9.5 + 0.1 * i as f64;
        // the stage lands on the nearest count (20 µm / 32767 = 0.6 nm)
        let want = bead([x, 10.0, 10.0]);
        let got = [r.scan.sx.data[[0, i]], r.scan.sz.data[[0, i]]];
        assert!(
            (got[0] - want[0]).abs() < 1e-3,
            "x = {x}: {got:?} vs {want:?}"
        );
        // Sz is the Sum in volts: 5 V · (1 + Sz_bead)
        assert!((got[1] - 5.0 * (1.0 + want[2])).abs() < 1e-3, "x = {x}");
    }
    // the bead's Sx changes sign across it
    assert!(r.scan.sx.data[[0, 2]] < -0.1 && r.scan.sx.data[[0, 8]] > 0.1);
}

#[test]
fn cube_that_stops_answering_mid_scan_ends_with_partial_scan_and_a_hold() {
    let k = kit(bead);
    let mut c = connected(&k, "");
    let limits = c.limits;
    let before = k.cubes[0].commands().len();
    // first point: SET_OUTPUTPOS + REQ_OUTPUTPOS polls; make the x cube fall silent after
    // serving the first three points' worth of messages is nondeterministic in polls, so count
    // from the 3rd SET: it is the 5th message if each move settles at the first poll
    k.cubes[0].faults().settle_s = Some(0.0);
    k.cubes[0].faults().silent_after = Some(4);
    let (r, saved) = run(&mut c.instrument, &line_x(9.0, 11.0, 5), &limits);
    let measured = match &r.ended {
        Ended::Failed {
            measured,
            error: DeviceError::Timeout {
                device, command, ..
            },
            stage_fault,
        } => {
            assert!(*stage_fault);
            assert!(
                device.starts_with("Thorlabs KPZ101 #29000001 (x) on /dev/pts/"),
                "{device}"
            );
            assert!(
                command.starts_with(
                    "MGMSG_PZ_REQ_OUTPUTPOS (after `0x0646 MGMSG_PZ_SET_OUTPUTPOS [01 00"
                ),
                "{command}"
            );
            *measured
        }
        other => panic!("{other:?}"),
    };
    assert_eq!(measured, 2);
    assert_eq!(saved.len(), 1);
    assert_eq!(saved[0].status, ScanStatus::Failed);
    let row: Vec<f64> = saved[0].sx.data.row(0).to_vec();
    assert!(
        row[..2].iter().all(|v| v.is_finite()) && row[2..].iter().all(|v| v.is_nan()),
        "{row:?}"
    );
    // the engine's stop: every cube holds; the silent x cube gets the hold at its last target
    // (10 µm = 0x4000) after its position request went unanswered; nothing moves after that
    std::thread::sleep(Duration::from_millis(50));
    let x = k.cubes[0].commands()[before..].to_vec();
    assert_eq!(
        x.last().unwrap(),
        "0x0646 MGMSG_PZ_SET_OUTPUTPOS [01 00 00 40]",
        "{x:?}"
    );
    assert_eq!(x[x.len() - 2], "0x0647 MGMSG_PZ_REQ_OUTPUTPOS (01, 00)");
    for cube in &k.cubes[1..] {
        let l = cube.commands();
        assert_eq!(l[l.len() - 2], "0x0647 MGMSG_PZ_REQ_OUTPUTPOS (01, 00)");
        assert_eq!(
            l.last().unwrap(),
            "0x0646 MGMSG_PZ_SET_OUTPUTPOS [01 00 00 40]"
        );
    }
    assert!(r
        .summary()
        .unwrap_err()
        .contains("the stage was not commanded further"));
}

/// A `Write` shared with the emulator thread.
#[derive(Clone, Default)]
struct SharedBuf(std::sync::Arc<std::sync::Mutex<Vec<u8>>>);

impl std::io::Write for SharedBuf {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(b);
        Ok(b.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

#[test]
fn emulate_thorlabs_prints_a_snippet_that_connects() {
    use bfpscope::instrument::emulator::run_emulator_cli_with;
    use std::sync::atomic::Ordering;
    let buf = SharedBuf::default();
    let stop = std::sync::Arc::new(AtomicBool::new(false));
    let h = {
        let (mut buf, stop) = (buf.clone(), stop.clone());
        std::thread::spawn(move || run_emulator_cli_with("thorlabs", standin_bead, &mut buf, stop))
    };
    let text = loop {
        let t = String::from_utf8_lossy(&buf.0.lock().unwrap()).into_owned();
        if t.contains("Serving until Ctrl-C.") {
            break t;
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let toml = text
        .split("# bfpscope.toml for these emulators:")
        .nth(1)
        .unwrap()
        .replace("Serving until Ctrl-C.", "");
    assert!(toml.contains("backend = \"kpz101\""), "{toml}");
    assert!(toml.contains("backend = \"kpa101\""), "{toml}");
    let cfg = Config::from_toml_str(&toml, "snippet").unwrap();
    let mut c = connect(&cfg, no_sim).unwrap();
    // the scene's origin is the middle of the travel; calibration: Sz = (Sum − 5 V)/5 V
    c.instrument.stage.move_to([10.1, 10.0, 10.0]).unwrap();
    let r = c.instrument.qpd.read(2).unwrap();
    let want = standin_bead([0.1, 0.0, 0.0]);
    assert!((r.sx - want[0]).abs() < 0.03, "{r} vs {want:?}");
    assert!((r.sz - want[2]).abs() < 0.03, "{r} vs {want:?}");
    drop(c);
    stop.store(true, Ordering::SeqCst);
    h.join().unwrap().unwrap();
    let e = run_emulator_cli_with("kpz999", standin_bead, &mut Vec::new(), stop)
        .unwrap_err()
        .to_string();
    assert!(
        e.starts_with("emulate: unknown device `kpz999` (expected `stage` (alias `gcs`), `qpd`,"),
        "{e}"
    );
}

#[test]
fn connect_thorlabs_at_the_prompt_names_the_cubes_and_the_aligner() {
    use bfpscope::script::{Settings, Workbench};
    let k = kit(bead);
    let dir = std::env::temp_dir().join(format!("bfpscope-apt-wb-{}", std::process::id()));
    cleanup::at_exit(&dir);
    let (s, _) = Settings::captured(&dir);
    let mut wb = Workbench::new(s);
    let line = wb
        .eval_source(
            "t",
            &format!(
                "connect(#{{backend: \"thorlabs\", stage_ports: #{{x: \"{}\", y: \"{}\", z: \"{}\"}}, qpd_port: \"{}\", timeout_ms: 300}})",
                k.cubes[0].path(),
                k.cubes[1].path(),
                k.cubes[2].path(),
                k.kpa.path()
            ),
        )
        .unwrap()
        .to_string();
    assert!(line.starts_with("connected hardware: "), "{line}");
    assert!(line.contains("KPZ101") && line.contains("KPA101"), "{line}");
    // the cubes start at 10 µm: the position reads back through the APT protocol
    let x = wb.eval_source("t", "pos().x").unwrap().as_float().unwrap();
    assert!((x - 10.0).abs() < 1e-3, "{x}");
    let e = wb
        .eval_source(
            "t",
            "connect(#{backend: \"thorlabs\", stage_ports: #{x: \"a\", y: \"b\"}})",
        )
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("stage_ports must be #{x: \"…\", y: \"…\", z: \"…\"} (z is missing)"),
        "{e}"
    );
    let e = wb
        .eval_source(
            "t",
            "connect(#{backend: \"thorlabs\", stage_port: \"/dev/x\"})",
        )
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("stage_port applies to backend \"hardware\" only"),
        "{e}"
    );
}
