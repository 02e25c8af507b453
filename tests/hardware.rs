//! The serial drivers against device emulators on pseudo-terminals: no hardware needed.
//!
//! Normal operation uses generous timeouts (a loaded CI machine must not make them flaky);
//! fault tests use 200 ms reply timeouts and check that every failure is bounded in time and
//! names the device, the command and what came back.

use crate::support::cleanup;
use bfpscope::instrument::{gcs::GCS, scpi::SCPI};

use bfpscope::acquire::{run_plan, Axis, Ended, Plan, ScanEnv, ScanError, SoftLimits, Sweep};
use bfpscope::config::connect::{connect, ConnectError};
use bfpscope::config::Config;
use bfpscope::data::{Scan, ScanStatus};
use bfpscope::instrument::emulator::{
    garble, run_emulator_cli_with, shared_position, sim_signal_source, standin_bead, start_pair,
    start_qpd_emulator, start_stage_emulator, Emulator, QpdEmulatorConfig, StageEmulatorConfig,
};
use bfpscope::instrument::gcs::{axes_xyz, GcsOptions, GcsStage};
use bfpscope::instrument::scpi::{Calibration, ScpiOptions, ScpiQpd};
use bfpscope::instrument::sim::scene::{Bead, Scene};
use bfpscope::instrument::sim::{SimConfig, SimCore};
use bfpscope::instrument::{
    DeviceError, Instrument, Pos, Qpd, QpdReading, RawQuery, Stage, VirtualClock,
};
use bfpscope::optics::params::Optics;
use std::io::{Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

const BAUD: u32 = 115_200;

fn opts(reply_ms: u64, on_target_ms: u64) -> GcsOptions {
    GcsOptions {
        timeout: Duration::from_millis(reply_ms),
        on_target_timeout: Duration::from_millis(on_target_ms),
        poll_interval: Duration::from_millis(1),
        ..GcsOptions::default()
    }
}

/// A stage emulator with a symmetric travel range and a fast settle.
fn stage_emu() -> Emulator {
    let cfg = StageEmulatorConfig {
        travel: [(-50.0, 50.0), (-40.0, 60.0), (0.0, 20.0)],
        settle_s: 0.005,
        ..StageEmulatorConfig::default()
    };
    start_stage_emulator(cfg, shared_position([0.0; 3])).unwrap()
}

fn open_stage(emu: &Emulator, reply_ms: u64) -> GcsStage {
    GcsStage::open(emu.path(), BAUD, opts(reply_ms, 2000)).unwrap()
}

const VPU: [f64; 3] = [2.0, 2.0, 4.0];
const OFFSET: [f64; 3] = [0.1, -0.1, 0.05];

/// The calibration that undoes the emulated detector's gain and offset.
fn inverse_calibration() -> Calibration {
    Calibration {
        gain: [1.0 / VPU[0], 1.0 / VPU[1], 1.0 / VPU[2]],
        offset_v: OFFSET,
    }
}

fn qpd_cfg(noise_v: f64) -> QpdEmulatorConfig {
    QpdEmulatorConfig {
        volts_per_unit: VPU,
        offset_v: OFFSET,
        noise_v: [noise_v; 3],
        ..Default::default()
    }
}

fn scpi_opts(reply_ms: u64) -> ScpiOptions {
    ScpiOptions {
        timeout: Duration::from_millis(reply_ms),
        calibration: inverse_calibration(),
        statistics: true,
        ..ScpiOptions::default()
    }
}

fn assert_bounded(t0: Instant, max_s: f64) {
    let dt = t0.elapsed().as_secs_f64();
    assert!(dt < max_s, "took {dt:.3} s (bound {max_s} s)");
}

// ---------------------------------------------------------------------------------------------
// GCS stage: normal operation

#[test]
fn stage_connect_identifies_and_switches_servo_on() {
    let emu = stage_emu();
    let s = open_stage(&emu, 1000);
    assert!(s.idn().contains("Physik Instrumente"), "{}", s.idn());
    assert_eq!(s.name(), format!("PI E-727 on {}", emu.path()));
    assert_eq!(
        emu.commands(),
        vec![
            "*IDN?",
            "ERR?",
            "SAI?",
            "SVO? 1 2 3",
            "MOV? 1 2 3",
            "SVO 1 1 2 1 3 1",
            "ERR?"
        ]
    );
}

#[test]
fn stage_move_and_position_round_trip() {
    let emu = stage_emu();
    let mut s = open_stage(&emu, 1000);
    let target = [12.5, -33.25, 7.125];
    s.move_to(target).unwrap();
    let p = s.position().unwrap();
    for i in 0..3 {
        assert!((p[i] - target[i]).abs() < 1e-6, "{p:?}");
    }
    assert_eq!(emu.position(), target);
    assert!(emu
        .commands()
        .contains(&"MOV 1 12.500000 2 -33.250000 3 7.125000".to_string()));
}

#[test]
fn stage_travel_range_from_tmn_tmx() {
    let emu = stage_emu();
    let mut s = open_stage(&emu, 1000);
    assert_eq!(
        s.travel_range().unwrap(),
        [(-50.0, 50.0), (-40.0, 60.0), (0.0, 20.0)]
    );
    let log = emu.commands();
    assert!(
        log.contains(&"TMN? 1 2 3".to_string()) && log.contains(&"TMX? 1 2 3".to_string()),
        "{log:?}"
    );
}

#[test]
fn stage_letter_axis_names() {
    // controllers named A B C (SAI? answers them) work when configured so
    let cfg = StageEmulatorConfig {
        axes: ["A".into(), "B".into(), "C".into()],
        ..Default::default()
    };
    let emu = start_stage_emulator(cfg, shared_position([0.0; 3])).unwrap();
    let o = GcsOptions {
        axes: axes_xyz(["A", "B", "C"]),
        ..opts(1000, 2000)
    };
    let mut s = GcsStage::open(emu.path(), BAUD, o).unwrap();
    assert_eq!(s.sai(), ["A", "B", "C"]);
    s.move_to([1.0, 2.0, 3.0]).unwrap();
    assert_eq!(s.position().unwrap(), [1.0, 2.0, 3.0]);
    assert!(emu.commands().contains(&"POS? A B C".to_string()));
    assert!(emu
        .commands()
        .contains(&"MOV A 1.000000 B 2.000000 C 3.000000".to_string()));
}

#[test]
fn stage_axis_map_swaps_axes() {
    // x on controller axis 2, y on 1: a move in x moves 2.
    let emu = stage_emu();
    let o = GcsOptions {
        axes: axes_xyz(["2", "1", "3"]),
        ..opts(1000, 2000)
    };
    let mut s = GcsStage::open(emu.path(), BAUD, o).unwrap();
    s.move_to([5.0, -7.0, 1.0]).unwrap();
    assert_eq!(emu.position(), [-7.0, 5.0, 1.0]); // emulator order is 1, 2, 3
    assert_eq!(s.position().unwrap(), [5.0, -7.0, 1.0]);
}

#[test]
fn stage_move_waits_for_on_target() {
    let emu = stage_emu();
    emu.faults().settle_s = Some(0.15);
    let mut s = open_stage(&emu, 1000);
    let t0 = Instant::now();
    s.move_to([10.0, 0.0, 0.0]).unwrap();
    let dt = t0.elapsed().as_secs_f64();
    assert!(
        dt >= 0.14,
        "returned after {dt} s, before the stage settled"
    );
    assert_bounded(t0, 3.0);
    let polls = emu.commands().iter().filter(|c| *c == "#5").count();
    assert!(polls >= 2, "#5 polled {polls} times");
    assert_eq!(s.position().unwrap(), [10.0, 0.0, 0.0]);
}

#[test]
fn stage_stop_halts_motion_where_it_is() {
    let emu = stage_emu();
    emu.faults().settle_s = Some(2.0);
    let mut s = open_stage(&emu, 1000);
    s.move_no_wait([40.0, 0.0, 0.0]).unwrap();
    std::thread::sleep(Duration::from_millis(100));
    s.stop().unwrap(); // error 10 "stopped" is expected and cleared
    let p1 = s.position().unwrap();
    assert!(p1[0] > 0.0 && p1[0] < 40.0, "{p1:?}");
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(s.position().unwrap(), p1, "still moving after STP");
    assert_eq!(s.on_target().unwrap(), [true; 3]);
    // The error register was cleared by the driver: the next command is clean.
    s.move_to(p1).unwrap();
}

// ---------------------------------------------------------------------------------------------
// GCS stage: faults

#[test]
fn fault_stage_no_reply_is_timeout_naming_device_and_command() {
    let emu = stage_emu();
    let mut s = open_stage(&emu, 200);
    emu.faults().silent = true;
    let t0 = Instant::now();
    match s.position() {
        Err(DeviceError::Timeout {
            device,
            command,
            timeout_ms,
        }) => {
            assert_eq!(device, format!("PI E-727 on {}", emu.path()));
            assert_eq!(command, "POS? 1 2 3");
            assert_eq!(timeout_ms, 200);
        }
        other => panic!("{other:?}"),
    }
    // one reply timeout + one ERR? probe
    assert_bounded(t0, 1.5);
    let e = s.move_to([1.0, 1.0, 1.0]).unwrap_err();
    assert!(
        e.to_string()
            .contains("ERR? (after `MOV 1 1.000000 2 1.000000 3 1.000000`)"),
        "{e}"
    );
    assert!(e.to_string().contains("no reply"), "{e}");
    // The device recovers: so does the driver. (A silent controller still executes what it
    // hears: the MOV went through although its ERR? got no answer.)
    emu.faults().silent = false;
    assert_eq!(s.position().unwrap(), [1.0; 3]);
}

#[test]
fn fault_stage_garbled_reply_is_garbled_with_the_text() {
    let emu = stage_emu();
    let mut s = open_stage(&emu, 200);
    s.move_to([12.5, 1.0, 2.0]).unwrap();
    emu.faults().garble_replies = 1;
    match s.position() {
        Err(DeviceError::Garbled {
            device,
            command,
            reply,
        }) => {
            assert!(device.contains(emu.path()));
            assert_eq!(command, "POS? 1 2 3");
            // the 0xFF byte shows as U+FFFD, digits became '#'
            assert_eq!(reply, "\u{FFFD}#=##.###### ");
        }
        other => panic!("{other:?}"),
    }
    // The next exchange resynchronises.
    assert_eq!(s.position().unwrap(), [12.5, 1.0, 2.0]);
    assert_eq!(garble("7"), vec![0xFF, b'#']);
}

#[test]
fn fault_stage_garbled_error_query_after_move() {
    let emu = stage_emu();
    let mut s = open_stage(&emu, 200);
    emu.faults().garble_replies = 1; // MOV has no reply: the ERR? reply is garbled
    match s.move_to([1.0, 2.0, 3.0]) {
        Err(DeviceError::Garbled { command, reply, .. }) => {
            assert_eq!(
                command,
                "ERR? (after `MOV 1 1.000000 2 2.000000 3 3.000000`)"
            );
            assert_eq!(reply, "\u{FFFD}#");
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn fault_stage_controller_error_code_with_text() {
    let emu = stage_emu();
    let mut s = open_stage(&emu, 200);
    emu.faults().error_next = Some(10);
    match s.move_to([1.0, 2.0, 3.0]) {
        Err(DeviceError::Controller {
            device,
            command,
            code,
            message,
        }) => {
            assert!(device.contains("E-727"));
            assert_eq!(command, "MOV 1 1.000000 2 2.000000 3 3.000000");
            assert_eq!(code, 10);
            assert_eq!(message, "Controller was stopped by command");
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(emu.position(), [0.0; 3], "a rejected MOV must not move");
    // The error was read (and so cleared): the same move now works.
    s.move_to([1.0, 2.0, 3.0]).unwrap();
}

#[test]
fn fault_stage_error_on_a_query_explains_the_silence() {
    // A controller does not answer a query it rejects; the driver asks ERR? and reports it.
    let emu = stage_emu();
    let mut s = open_stage(&emu, 200);
    emu.faults().error_next = Some(15);
    match s.position() {
        Err(DeviceError::Controller {
            command,
            code,
            message,
            ..
        }) => {
            assert_eq!(
                (command.as_str(), code, message.as_str()),
                ("POS? 1 2 3", 15, "Invalid axis identifier")
            );
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn fault_stage_servo_off_is_error_5() {
    let emu = stage_emu();
    let o = GcsOptions {
        servo_on_connect: false,
        ..opts(1000, 2000)
    };
    let mut s = GcsStage::open(emu.path(), BAUD, o).unwrap();
    match s.move_to([1.0, 0.0, 0.0]) {
        Err(DeviceError::Controller {
            code: 5, message, ..
        }) => assert!(message.contains("servo off")),
        other => panic!("{other:?}"),
    }
    s.set_servo(true).unwrap();
    s.move_to([1.0, 0.0, 0.0]).unwrap();
}

#[test]
fn fault_stage_out_of_range_target_is_the_controllers_error_7() {
    // The driver refuses nothing itself (the pre-flight limit check lives in acquire/): the
    // command goes out and the controller's own error 7 comes back as a Controller error.
    let emu = stage_emu();
    let mut s = open_stage(&emu, 1000);
    s.move_to([5.0, 5.0, 5.0]).unwrap();
    match s.move_to([75.0, 5.0, 5.0]) {
        Err(DeviceError::Controller {
            command,
            code,
            message,
            ..
        }) => {
            // only the axis that changes is named
            assert_eq!(command, "MOV 1 75.000000");
            assert_eq!((code, message.as_str()), (7, "Position out of limits"));
        }
        other => panic!("{other:?}"),
    }
    assert!(emu.commands().contains(&"MOV 1 75.000000".to_string()));
    assert_eq!(
        s.position().unwrap(),
        [5.0, 5.0, 5.0],
        "the stage must not have moved"
    );
}

#[test]
fn fault_stage_clamping_controller_when_rejection_is_off() {
    let emu = stage_emu();
    emu.faults().reject_out_of_range = false;
    let mut s = open_stage(&emu, 1000);
    s.move_to([75.0, 5.0, 25.0]).unwrap();
    assert_eq!(s.position().unwrap(), [50.0, 5.0, 20.0]);
}

#[test]
fn fault_stage_slow_settling_is_an_on_target_timeout() {
    let emu = stage_emu();
    let mut s = GcsStage::open(emu.path(), BAUD, opts(200, 300)).unwrap();
    emu.faults().settle_s = Some(30.0);
    let t0 = Instant::now();
    let e = s.move_to([20.0, 0.0, 0.0]).unwrap_err();
    assert_bounded(t0, 2.0);
    match &e {
        DeviceError::Other { device, detail } => {
            assert!(device.contains("E-727"));
            assert!(
                detail.starts_with("not on target within 300 ms after `MOV 1 20.000000`"),
                "{detail}"
            );
            assert!(
                detail.ends_with("(last `#5` reply: 1=0 2=1 3=1)"),
                "{detail}"
            );
        }
        other => panic!("{other:?}"),
    }
    let p = s.position().unwrap();
    assert!(p[0] > 0.0 && p[0] < 1.0, "{p:?}");
}

#[test]
fn fault_stage_unplugged_mid_sequence_is_disconnected() {
    let emu = stage_emu();
    let mut s = open_stage(&emu, 200);
    // With instant settling the first move is MOV, ERR?, #5, ONT? 1 (`#5` is not known to
    // work yet), later ones MOV, #5, ONT? 1, ERR? (the ERR? once the trajectory has ended; the
    // `ONT?` confirms on target), and the first call (to where the stage already
    // is) sends nothing: unplug right after the 3rd MOV, the 4th call's; its `#5` finds the
    // line dead.
    emu.faults().settle_s = Some(0.0);
    emu.faults().unplug_after = Some(9);
    let t0 = Instant::now();
    let mut done = 0;
    let err = loop {
        match s.move_to([done as f64, 0.0, 0.0]) {
            Ok(()) => done += 1,
            Err(e) => break e,
        }
        assert!(done < 10, "never unplugged");
    };
    assert_bounded(t0, 2.0);
    assert_eq!(done, 3, "{err}");
    match &err {
        DeviceError::Disconnected {
            device, command, ..
        } => {
            assert!(device.contains(emu.path()));
            assert_eq!(command, "#5");
        }
        other => panic!("{other:?}"),
    }
    assert!(!emu.is_running());
    // Further calls keep failing cleanly.
    assert!(matches!(
        s.position(),
        Err(DeviceError::Disconnected { .. })
    ));
}

#[test]
fn cr_lf_line_endings_read_the_same_values() {
    let emu = stage_emu();
    emu.faults().crlf = true;
    let mut s = open_stage(&emu, 200);
    // connect read IDN, SAI?, SVO?, MOV?, TMN?/TMX? through CR LF replies
    assert_eq!(
        s.travel_range().unwrap(),
        [(-50.0, 50.0), (-40.0, 60.0), (0.0, 20.0)]
    );
    s.move_to([1.25, -2.5, 3.0]).unwrap();
    assert_eq!(s.position().unwrap(), [1.25, -2.5, 3.0]);
    assert_eq!(s.target().unwrap(), [1.25, -2.5, 3.0]);
    // a multi-line reply: no CR left on any line
    let lines = s.raw_query("SAI?").unwrap();
    assert_eq!(lines, ["1", "2", "3"]);
    assert!(emu.commands().iter().any(|c| c == "SAI?"));
}

/// A fake controller on a raw PTY: answers `*IDN?`/`ERR?`/`SAI?`/`SVO?`/`MOV?` properly and every `POS?`
/// with the next scripted reply.
fn fake_controller(
    replies: Vec<Vec<u8>>,
) -> (String, std::thread::JoinHandle<()>, Arc<AtomicBool>) {
    let (mut master, slave) = serialport::TTYPort::pair().unwrap();
    let path = serialport::SerialPort::name(&slave).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let stop2 = stop.clone();
    let h = std::thread::spawn(move || {
        let _slave = slave;
        serialport::SerialPort::set_timeout(&mut master, Duration::from_millis(5)).unwrap();
        let mut replies = replies.into_iter();
        let mut buf = Vec::new();
        while !stop2.load(Ordering::SeqCst) {
            let mut chunk = [0u8; 256];
            if let Ok(n) = master.read(&mut chunk) {
                buf.extend_from_slice(&chunk[..n]);
            }
            while let Some(i) = buf.iter().position(|&b| b == b'\n') {
                let line: Vec<u8> = buf.drain(..=i).collect();
                let reply: Vec<u8> = match &line[..line.len() - 1] {
                    b"*IDN?" => b"PI, C-413, 1, 1\n".to_vec(),
                    b"ERR?" => b"0\n".to_vec(),
                    b"SAI?" => b"1 \n2 \n3\n".to_vec(),
                    l if l.starts_with(b"SVO?") => b"1=0 \n2=0 \n3=0\n".to_vec(),
                    l if l.starts_with(b"MOV?") => b"1=0 \n2=0 \n3=0\n".to_vec(),
                    l if l.starts_with(b"POS?") => replies.next().unwrap_or_default(),
                    _ => vec![],
                };
                let _ = master.write_all(&reply);
            }
        }
    });
    (path, h, stop)
}

#[test]
fn fault_stage_garbage_replies_never_panic() {
    let garbage: Vec<Vec<u8>> = vec![
        b"1=1 \n2=zz\n3=3\n".to_vec(),
        b"\x00\x01\x02\x03\n".to_vec(),
        b"1=1e999 \n2=0 \n3=0\n".to_vec(),
        b"1=1 \n1=1 \n2=1\n".to_vec(),
        b"X=1 \n2=0 \n3=0\n".to_vec(),
        vec![b'7'; 4200],
        b"1=1 \n2=2 \n3=3\n".to_vec(),
    ];
    let (path, h, stop) = fake_controller(garbage);
    let mut s = GcsStage::open(
        &path,
        BAUD,
        GcsOptions {
            servo_on_connect: false,
            ..opts(200, 300)
        },
    )
    .unwrap();
    assert_eq!(s.name(), format!("PI C-413 on {path}"));
    for k in 0..6 {
        match s.position() {
            Err(DeviceError::Garbled { command, .. }) => assert_eq!(command, "POS? 1 2 3"),
            other => panic!("garbage #{k}: {other:?}"),
        }
    }
    assert_eq!(s.position().unwrap(), [1.0, 2.0, 3.0]);
    stop.store(true, Ordering::SeqCst);
    h.join().unwrap();
}

// ---------------------------------------------------------------------------------------------
// SCPI QPD

fn qpd_emu(noise_v: f64, at: Pos) -> Emulator {
    start_qpd_emulator(qpd_cfg(noise_v), shared_position(at), standin_bead).unwrap()
}

#[test]
fn qpd_connect_identify_and_read_calibrated_signal() {
    let at = [0.2, -0.1, 0.3];
    let emu = qpd_emu(0.0, at);
    let mut q = ScpiQpd::open(emu.path(), BAUD, scpi_opts(1000)).unwrap();
    assert_eq!(q.idn(), "bfpscope,QPD-EMU,0001,1.0");
    assert_eq!(q.name(), format!("QPD QPD-EMU on {}", emu.path()));
    assert_eq!(q.sample_rate(), 100_000.0);
    let r = q.read(50).unwrap();
    let want = standin_bead(at);
    for (got, want) in [(r.sx, want[0]), (r.sy, want[1]), (r.sz, want[2])] {
        assert!((got - want).abs() < 1e-9, "{r} vs {want:?}");
    }
    assert_eq!(r.n, 50);
    assert_eq!((r.sx_std, r.sy_std, r.sz_std), (0.0, 0.0, 0.0));
    // the averaging count is only sent when it changes
    q.read(50).unwrap();
    let log = emu.commands();
    assert_eq!(
        log.iter()
            .filter(|c| c.starts_with("SENS:AVER:COUN"))
            .count(),
        1,
        "{log:?}"
    );
    assert_eq!(&log[..4], ["*IDN?", "*CLS", "SYST:ERR?", "CONF:RATE?"]);
}

/// A signal beyond the digitiser's input range: the emulated converter reads the rail, and
/// the driver (told `range_v`) counts every sample of that channel as clipped; the channels
/// within the range count none. Without `range_v` nothing is counted (the range unknown).
#[test]
fn qpd_samples_at_the_input_range_are_counted_as_clipped() {
    // Sx 2.0 units × 2 V + 0.1 V = 4.1 V against ±1 V; Sy 0.1 × 2 − 0.1 = 0.1 V; Sz 0.05 V
    let cfg = QpdEmulatorConfig {
        range_v: Some(1.0),
        ..qpd_cfg(0.0)
    };
    let emu = start_qpd_emulator(cfg, shared_position([0.0; 3]), |_: Pos| [2.0, 0.1, 0.0]).unwrap();
    let o = ScpiOptions {
        range_v: Some(1.0),
        ..scpi_opts(1000)
    };
    let mut q = ScpiQpd::open(emu.path(), BAUD, o).unwrap();
    let r = q.read(40).unwrap();
    assert_eq!(r.clipped, [40, 0, 0], "{r}");
    // the railed mean: (1 V − 0.1 V) / 2 V per unit, not the scene's 2.0
    assert!((r.sx - 0.45).abs() < 1e-9, "{r}");
    assert!((r.sy - 0.1).abs() < 1e-9, "{r}");
    let range = q.input_range().expect("the range is known");
    assert_eq!(range.full_scale, 1.0);
    drop(q);
    let emu = start_qpd_emulator(
        QpdEmulatorConfig {
            range_v: Some(1.0),
            ..qpd_cfg(0.0)
        },
        shared_position([0.0; 3]),
        |_: Pos| [2.0, 0.1, 0.0],
    )
    .unwrap();
    let mut q = ScpiQpd::open(emu.path(), BAUD, scpi_opts(1000)).unwrap();
    assert_eq!(q.read(40).unwrap().clipped, [0, 0, 0]);
}

#[test]
fn qpd_noise_statistics_in_signal_units() {
    let emu = qpd_emu(0.02, [0.0; 3]);
    let mut q = ScpiQpd::open(emu.path(), BAUD, scpi_opts(1000)).unwrap();
    let r = q.read(2000).unwrap();
    // per-sample std is 0.02 V → 0.01 units on x (gain 1/2), 0.005 on z (gain 1/4)
    assert!((r.sx_std - 0.01).abs() < 0.001, "{r}");
    assert!((r.sz_std - 0.005).abs() < 0.0005, "{r}");
    // the mean of 2000 samples is within 5 σ/√n of the true value (0, 0, 0.2)
    assert!(r.sx.abs() < 5.0 * 0.01 / 2000f64.sqrt(), "{r}");
    assert!((r.sz - 0.2).abs() < 5.0 * 0.005 / 2000f64.sqrt(), "{r}");
}

#[test]
fn qpd_without_statistics_uses_meas_qpd() {
    let emu = qpd_emu(0.0, [0.1, 0.0, 0.0]);
    let o = ScpiOptions {
        statistics: false,
        ..scpi_opts(1000)
    };
    let mut q = ScpiQpd::open(emu.path(), BAUD, o).unwrap();
    let r = q.read(10).unwrap();
    assert!((r.sx - standin_bead([0.1, 0.0, 0.0])[0]).abs() < 1e-9);
    assert!(emu.commands().contains(&"MEAS:QPD?".to_string()));
}

#[test]
fn fault_qpd_device_error_queue() {
    let emu = qpd_emu(0.0, [0.0; 3]);
    let mut q = ScpiQpd::open(emu.path(), BAUD, scpi_opts(200)).unwrap();
    match q.read(0) {
        Err(DeviceError::Controller {
            device,
            command,
            code,
            message,
        }) => {
            assert!(device.contains(emu.path()));
            assert_eq!(command, "SENS:AVER:COUN 0");
            assert_eq!((code, message.as_str()), (-222, "Data out of range"));
        }
        other => panic!("{other:?}"),
    }
    match q.command("SENS:AVER:COUN many") {
        Err(DeviceError::Controller {
            code: -104,
            message,
            ..
        }) => assert_eq!(message, "Data type error"),
        other => panic!("{other:?}"),
    }
    match q.query("MEAS:VOLT?") {
        Err(DeviceError::Controller {
            code: -113,
            command,
            message,
            ..
        }) => {
            assert_eq!(
                (command.as_str(), message.as_str()),
                ("MEAS:VOLT?", "Undefined header")
            );
        }
        other => panic!("{other:?}"),
    }
    // The queue is empty again and reads work.
    q.read(5).unwrap();
}

#[test]
fn fault_qpd_injected_error_on_measurement() {
    let emu = qpd_emu(0.0, [0.0; 3]);
    let mut q = ScpiQpd::open(emu.path(), BAUD, scpi_opts(200)).unwrap();
    q.read(5).unwrap();
    emu.faults().error_next = Some(-231);
    match q.read(5) {
        Err(DeviceError::Controller {
            command,
            code,
            message,
            ..
        }) => {
            assert_eq!((command.as_str(), code), ("MEAS:QPD:STAT?", -231));
            assert_eq!(message, "Device-specific error");
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn fault_qpd_no_reply_is_timeout() {
    let emu = qpd_emu(0.0, [0.0; 3]);
    let mut q = ScpiQpd::open(emu.path(), BAUD, scpi_opts(200)).unwrap();
    q.read(10).unwrap();
    emu.faults().silent = true;
    let t0 = Instant::now();
    match q.read(10) {
        Err(DeviceError::Timeout {
            device,
            command,
            timeout_ms,
        }) => {
            assert!(device.contains("QPD-EMU"));
            assert_eq!(command, "MEAS:QPD:STAT?");
            assert_eq!(timeout_ms, 200); // 200 ms + 10 samples at 100 kHz
        }
        other => panic!("{other:?}"),
    }
    assert_bounded(t0, 1.5);
}

#[test]
fn fault_qpd_garbled_reply() {
    let emu = qpd_emu(0.0, [0.1, 0.0, 0.0]);
    let mut q = ScpiQpd::open(emu.path(), BAUD, scpi_opts(200)).unwrap();
    q.read(10).unwrap();
    emu.faults().garble_replies = 1;
    match q.read(10) {
        Err(DeviceError::Garbled { command, reply, .. }) => {
            assert_eq!(command, "MEAS:QPD:STAT?");
            assert!(
                reply.starts_with('\u{FFFD}') && reply.contains("#.#########e-#"),
                "{reply}"
            );
        }
        other => panic!("{other:?}"),
    }
    q.read(10).unwrap();
}

#[test]
fn fault_qpd_unplugged_is_disconnected() {
    let emu = qpd_emu(0.0, [0.0; 3]);
    let mut q = ScpiQpd::open(emu.path(), BAUD, scpi_opts(200)).unwrap();
    emu.faults().unplug_after = Some(0);
    let t0 = Instant::now();
    while emu.is_running() {
        assert_bounded(t0, 1.0);
        std::thread::sleep(Duration::from_millis(2));
    }
    match q.read(10) {
        Err(DeviceError::Disconnected {
            device, command, ..
        }) => {
            assert!(device.contains(emu.path()));
            assert!(command.starts_with("SENS:AVER:COUN 10"), "{command}");
        }
        other => panic!("{other:?}"),
    }
}

// ---------------------------------------------------------------------------------------------
// Config, connect, scans

fn emulator_config(stage: &Emulator, qpd: &Emulator) -> Config {
    Config::from_toml_str(&emulator_config_text(stage, qpd), "test.toml").unwrap()
}

fn emulator_config_text(stage: &Emulator, qpd: &Emulator) -> String {
    format!(
        r#"
[stage]
backend = "gcs"
port = "{}"
timeout_ms = 1000
on_target_timeout_ms = 2000
poll_ms = 1
settle_s = 0.0

[qpd]
backend = "scpi"
port = "{}"
calibration = {{ gain = [{}, {}, {}], offset_v = [{}, {}, {}] }}

[safety]
soft_limits = {{ x = [-1.0, 1.0], z = [-5.0, 0.5] }}
max_step_um = 2.0
"#,
        stage.path(),
        qpd.path(),
        1.0 / VPU[0],
        1.0 / VPU[1],
        1.0 / VPU[2],
        OFFSET[0],
        OFFSET[1],
        OFFSET[2]
    )
}

fn pair(noise_v: f64) -> (Emulator, Emulator) {
    let stage = StageEmulatorConfig {
        travel: [(-2.0, 2.0), (-2.0, 2.0), (-1.0, 1.0)],
        settle_s: 0.001,
        ..Default::default()
    };
    start_pair(stage, qpd_cfg(noise_v), standin_bead).unwrap()
}

fn no_sim(_: &Config) -> anyhow::Result<Instrument> {
    panic!("the simulator must not be built for a hardware config")
}

#[test]
fn connect_hardware_from_config_intersects_soft_limits() {
    let (se, qe) = pair(0.0);
    let cfg = emulator_config(&se, &qe);
    let c = connect(&cfg, no_sim).unwrap();
    assert_eq!(
        c.limits,
        SoftLimits {
            range: [(-1.0, 1.0), (-2.0, 2.0), (-1.0, 0.5)],
            max_step_um: 2.0,
            max_speed_um_s: None
        }
    );
    let d = &c.instrument.description;
    assert_eq!(d["stage"]["backend"], "gcs");
    assert_eq!(d["stage"]["port"], se.path());
    assert_eq!(d["qpd"]["sample_rate_hz"], 100_000.0);
    assert!(d["stage"]["idn"].as_str().unwrap().contains("E-727"));
    assert_eq!(d["limits"]["range"][0], serde_json::json!([-1.0, 1.0]));
    assert_eq!(d["backend"], "hardware");
    assert!(!c.instrument.clock.is_virtual());
}

#[test]
fn connect_soft_limits_outside_travel_is_a_config_error() {
    let (se, qe) = pair(0.0);
    let mut cfg = emulator_config(&se, &qe);
    cfg.safety.soft_limits.y = Some([5.0, 9.0]);
    match connect(&cfg, no_sim) {
        Err(ConnectError::Config(e)) => {
            assert_eq!(e.key, "safety.soft_limits.y");
            assert!(e.message.contains("travel range [-2, 2]"), "{e}");
        }
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("connected"),
    }
}

#[test]
fn connect_missing_port_names_device_and_port() {
    let mut cfg = Config::default();
    cfg.stage.backend = GCS;
    cfg.stage.port = Some("/dev/bfpscope-no-such-port".into());
    cfg.qpd.backend = SCPI;
    cfg.qpd.port = Some("/dev/bfpscope-no-such-qpd".into());
    let e = connect(&cfg, no_sim).err().expect("must fail");
    let msg = e.to_string();
    assert!(
        matches!(e, ConnectError::Device(DeviceError::Other { .. })),
        "{msg}"
    );
    assert!(
        msg.starts_with(
            "GCS stage on /dev/bfpscope-no-such-port: cannot open /dev/bfpscope-no-such-port"
        ),
        "{msg}"
    );
}

#[test]
fn connect_qpd_failure_closes_the_stage_port() {
    let se = stage_emu();
    let mut cfg = Config::default();
    cfg.stage.backend = GCS;
    cfg.stage.port = Some(se.path().into());
    cfg.qpd.backend = SCPI;
    cfg.qpd.port = Some("/dev/bfpscope-no-such-qpd".into());
    let e = connect(&cfg, no_sim).err().expect("must fail");
    assert!(
        e.to_string()
            .starts_with("SCPI QPD on /dev/bfpscope-no-such-qpd: cannot open"),
        "{e}"
    );
    // The stage port was released: it opens again.
    let _s = open_stage(&se, 1000);
}

/// A minimal stand-in for the simulated backend, to check `connect`'s sim path.
struct FakeStage(Pos);
impl Stage for FakeStage {
    fn name(&self) -> String {
        "fake stage".into()
    }
    fn position(&mut self) -> Result<Pos, DeviceError> {
        Ok(self.0)
    }
    fn move_to(&mut self, t: Pos) -> Result<(), DeviceError> {
        self.0 = t;
        Ok(())
    }
    fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError> {
        Ok([(0.0, 80.0), (0.0, 80.0), (0.0, 10.0)])
    }
    fn stop(&mut self) -> Result<(), DeviceError> {
        Ok(())
    }
}
struct FakeQpd;
impl Qpd for FakeQpd {
    fn name(&self) -> String {
        "fake qpd".into()
    }
    fn sample_rate(&self) -> f64 {
        1.0
    }
    fn read(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        Ok(QpdReading {
            n,
            ..Default::default()
        })
    }
}

#[test]
fn connect_without_config_builds_the_simulator() {
    let cfg = Config::from_toml_str("[safety]\nsoft_limits = { z = [2.0, 8.0] }\n", "t").unwrap();
    let mut called = false;
    let c = connect(&cfg, |c| {
        called = true;
        Ok(Instrument {
            stage: Box::new(FakeStage([0.0; 3])),
            qpd: Box::new(FakeQpd),
            clock: Arc::new(VirtualClock::new()),
            settle_s: c.stage.settle_s,
            description: serde_json::json!({"backend": "sim"}),
        })
    })
    .unwrap();
    assert!(called);
    assert_eq!(c.limits.range, [(0.0, 80.0), (0.0, 80.0), (2.0, 8.0)]);
    assert_eq!(c.instrument.settle_s, 0.005);
    assert_eq!(c.instrument.description["backend"], "sim");
}

/// Raster an image of Sx through the real drivers; returns (positions, readings).
fn raster(inst: &mut Instrument, n: usize, half: f64, samples: usize) -> Vec<(Pos, QpdReading)> {
    let mut out = Vec::new();
    for j in 0..n {
        for i in 0..n {
            let x = -half + 2.0 * half * i as f64 / (n - 1) as f64;
            let y = -half + 2.0 * half * j as f64 / (n - 1) as f64;
            let p = [x, y, 0.0];
            inst.move_settle(p).unwrap();
            out.push((p, inst.qpd.read(samples).unwrap()));
        }
    }
    out
}

#[test]
fn scan_through_the_real_drivers_images_the_standin_bead() {
    let noise_v = 0.004;
    let (se, qe) = pair(noise_v);
    let cfg = emulator_config(&se, &qe);
    let mut c = connect(&cfg, no_sim).unwrap();
    let samples = 100;
    let img = raster(&mut c.instrument, 11, 0.6, samples);
    // expected σ of a mean, in signal units (gain 1/2 on x, y; 1/4 on z)
    let sig = |vpu: f64| noise_v / vpu / (samples as f64).sqrt();
    let mut max_sx = f64::MIN;
    let mut chi2 = 0.0;
    for (p, r) in &img {
        let want = standin_bead(*p);
        for (got, want, s) in [
            (r.sx, want[0], sig(VPU[0])),
            (r.sy, want[1], sig(VPU[1])),
            (r.sz, want[2], sig(VPU[2])),
        ] {
            assert!(
                (got - want).abs() < 5.0 * s,
                "at {p:?}: {got} vs {want} (σ {s})"
            );
            chi2 += ((got - want) / s).powi(2);
        }
        max_sx = max_sx.max(r.sx);
    }
    // the residuals are noise of the expected size, not zero and not larger
    let dof = 3.0 * img.len() as f64;
    assert!(
        chi2 / dof > 0.6 && chi2 / dof < 1.5,
        "χ²/dof = {}",
        chi2 / dof
    );
    // and the image has the bead in it: Sx peaks near x = 0.28 at y = 0 (0.28·e^-0.5 ≈ 0.17)
    assert!(max_sx > 0.15, "{max_sx}");
    // the stage went where the plan said: the last point
    assert_eq!(se.position(), [0.6, 0.6, 0.0]);
}

#[test]
fn scan_of_a_simulated_bead_through_the_drivers_matches_the_simulator() {
    // One scene, two instruments: the simulator itself, and the real drivers talking to
    // emulators whose QPD answers with the simulator's signal at the emulated stage position.
    let mut scene = Scene::default();
    scene
        .add_bead(Bead {
            pos: [0.1, -0.05, 0.0],
            d_nm: 200.0,
            n: 1.572,
        })
        .unwrap();
    let core = SimCore::new(&Optics::default(), &scene, SimConfig::default()).unwrap();
    let mut sim = core.instrument(0.0);
    let (n, half, samples) = (9, 0.5, 100);
    let sim_img = raster(&mut sim, n, half, samples);
    let amp = sim_img.iter().map(|(_, r)| r.sx.abs()).fold(0.0, f64::max);
    assert!(
        amp > 0.0 && amp.is_finite(),
        "simulated bead gives no signal: {amp}"
    );

    // emulated detector: 5 V per signal unit, noise such that one averaged reading has σ = 1 % of
    // the Sx amplitude
    let vpu = 5.0;
    let sigma = 0.01 * amp;
    let noise_v = sigma * vpu * (samples as f64).sqrt();
    let qcfg = QpdEmulatorConfig {
        volts_per_unit: [vpu; 3],
        noise_v: [noise_v; 3],
        ..Default::default()
    };
    let scfg = StageEmulatorConfig {
        settle_s: 0.001,
        ..StageEmulatorConfig::like_sim(&core.cfg)
    };
    assert_eq!(scfg.travel, SimConfig::default().travel);
    let (se, qe) = start_pair(scfg, qcfg, sim_signal_source(core.renderer())).unwrap();
    let mut cfg = emulator_config(&se, &qe);
    cfg.qpd.calibration = Calibration {
        gain: [1.0 / vpu; 3],
        offset_v: [0.0; 3],
    };
    let mut hw = connect(&cfg, no_sim).unwrap();
    let hw_img = raster(&mut hw.instrument, n, half, samples);

    let mut chi2 = 0.0;
    for ((p, a), (q, b)) in sim_img.iter().zip(&hw_img) {
        assert_eq!(p, q);
        for (got, want) in [(b.sx, a.sx), (b.sy, a.sy), (b.sz, a.sz)] {
            assert!(
                (got - want).abs() < 5.0 * sigma,
                "at {p:?}: drivers {got} vs simulator {want} (σ {sigma})"
            );
            chi2 += ((got - want) / sigma).powi(2);
        }
    }
    let dof = 3.0 * sim_img.len() as f64;
    assert!(
        chi2 / dof > 0.6 && chi2 / dof < 1.5,
        "χ²/dof = {}",
        chi2 / dof
    );
}

#[test]
fn scan_unplugged_mid_scan_stops_with_disconnected() {
    let (se, qe) = pair(0.0);
    let cfg = emulator_config(&se, &qe);
    let mut c = connect(&cfg, no_sim).unwrap();
    // after 3 points: COUN and its ERR? once, then one STAT? per point (a well-formed reply
    // needs no SYST:ERR?)
    qe.faults().unplug_after = Some(5);
    let mut got = 0;
    let err = loop {
        let p = [-0.5 + 0.1 * got as f64, 0.0, 0.0];
        if let Err(e) = c.instrument.move_settle(p) {
            break e;
        }
        match c.instrument.qpd.read(10) {
            Ok(_) => got += 1,
            Err(e) => break e,
        }
        assert!(got < 20, "never unplugged");
    };
    assert!(matches!(err, DeviceError::Disconnected { .. }), "{err}");
    assert_eq!(got, 3, "{err}");
    // the stage still answers: the scan engine can decide what to do with it
    assert_eq!(c.instrument.stage.position().unwrap(), [-0.2, 0.0, 0.0]);
}

#[test]
fn emulator_stops_on_drop_and_the_driver_sees_disconnected() {
    let mut emu = stage_emu();
    let mut s = open_stage(&emu, 200);
    let t0 = Instant::now();
    emu.stop();
    assert_bounded(t0, 1.0);
    assert!(!emu.is_running());
    assert!(matches!(
        s.position(),
        Err(DeviceError::Disconnected { .. })
    ));
}

#[test]
fn emulate_cli_prints_paths_that_work() {
    struct Chan(mpsc::Sender<Vec<u8>>);
    impl Write for Chan {
        fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
            let _ = self.0.send(b.to_vec());
            Ok(b.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }
    let (tx, rx) = mpsc::channel();
    let stop = Arc::new(AtomicBool::new(false));
    let stop2 = stop.clone();
    let h = std::thread::spawn(move || {
        run_emulator_cli_with("both", standin_bead, &mut Chan(tx), stop2)
    });
    let mut text = String::new();
    let t0 = Instant::now();
    while !text.contains("Serving until") {
        assert_bounded(t0, 5.0);
        if let Ok(b) = rx.recv_timeout(Duration::from_millis(100)) {
            text.push_str(&String::from_utf8_lossy(&b));
        }
    }
    let path_of = |kind: &str| {
        let line = text.lines().find(|l| l.starts_with(kind)).unwrap();
        line.rsplit(" on ").next().unwrap().to_string()
    };
    let (sp, qp) = (path_of("stage:"), path_of("qpd:"));
    assert!(
        sp.starts_with("/dev/") && qp.starts_with("/dev/") && sp != qp,
        "{text}"
    );
    // the printed config snippet parses and points at the emulators
    let toml_part = text
        .split("# bfpscope.toml for these emulators:")
        .nth(1)
        .unwrap();
    let toml_part = toml_part.split("Serving until").next().unwrap();
    let cfg = Config::from_toml_str(toml_part, "snippet").unwrap();
    assert_eq!(cfg.stage.port.as_deref(), Some(sp.as_str()));
    let mut s = GcsStage::open(&sp, BAUD, opts(1000, 2000)).unwrap();
    s.move_to([0.1, 0.0, 0.0]).unwrap();
    let mut q = ScpiQpd::open(&qp, BAUD, ScpiOptions::default()).unwrap();
    let r = q.read(10).unwrap();
    assert!(
        (r.sx - standin_bead([0.1, 0.0, 0.0])[0]).abs() < 5e-4,
        "{r}"
    );
    stop.store(true, Ordering::SeqCst);
    h.join().unwrap().unwrap();
    let e = run_emulator_cli_with("laser", standin_bead, &mut Vec::new(), stop)
        .unwrap_err()
        .to_string();
    assert!(
        e.starts_with("emulate: unknown device `laser` (expected `stage` (alias `gcs`), `qpd`,"),
        "{e}"
    );
}

// ---------------------------------------------------------------------------------------------
// Through the scan engine (acquire/): its safety rules hold on the real drivers

/// Connect to a fresh emulator pair from a config file text, with the rules of its `[safety]`
/// table (the one parse).
fn engine_setup() -> (
    Emulator,
    Emulator,
    bfpscope::config::connect::Connected,
    SoftLimits,
) {
    let (se, qe) = pair(0.0);
    let text = emulator_config_text(&se, &qe);
    let cfg = Config::from_toml_str(&text, "test.toml").unwrap();
    let limits = cfg.soft_limits();
    assert_eq!(limits.range[0], (-1.0, 1.0));
    assert_eq!(limits.max_step_um, 2.0);
    let c = connect(&cfg, no_sim).unwrap();
    (se, qe, c, limits)
}

/// Run a plan, collecting log lines and the autosaved scans.
fn run(
    inst: &mut Instrument,
    plan: &Plan,
    limits: &SoftLimits,
) -> (Result<bfpscope::acquire::ScanRun, ScanError>, Vec<Scan>) {
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

fn line_x(from: f64, to: f64, n: i64, rel: bool) -> Plan {
    let kind = if rel { "dscan" } else { "ascan" };
    Plan::line(
        kind,
        Sweep::new(kind, Axis::X, from, to, n, "n").unwrap(),
        1e-4,
        rel,
    )
    .unwrap()
}

#[test]
fn engine_scan_through_the_drivers_completes() {
    let (se, _qe, mut c, limits) = engine_setup();
    let (r, saved) = run(&mut c.instrument, &line_x(-0.5, 0.5, 5, false), &limits);
    let r = r.unwrap();
    assert_eq!(r.ended, Ended::Complete);
    assert_eq!(saved.len(), 1);
    for (i, x) in [-0.5, -0.25, 0.0, 0.25, 0.5].iter().enumerate() {
        let want = standin_bead([*x, 0.0, 0.0])[0];
        assert!((r.scan.sx.data[[0, i]] - want).abs() < 1e-9, "x = {x}");
    }
    assert_eq!(se.position(), [0.5, 0.0, 0.0]);
}

#[test]
fn engine_refuses_an_out_of_limits_plan_before_anything_is_sent() {
    // x soft limit [-1, 1] (travel is [-2, 2]): the driver would send this and the controller
    // would accept it; the engine's pre-flight refuses it first.
    let (se, _qe, mut c, limits) = engine_setup();
    let before = se.commands().len();
    let (r, saved) = run(&mut c.instrument, &line_x(0.0, 1.5, 4, false), &limits);
    match r {
        Err(ScanError::Refused(msg)) => {
            assert!(msg.contains("refused before any move"), "{msg}");
            assert!(
                msg.contains("x = 1.5 µm is above the soft limit x ≤ 1 µm"),
                "{msg}"
            );
        }
        other => panic!("{:?}", other.map(|r| r.ended)),
    }
    assert!(saved.is_empty());
    let sent = &se.commands()[before..];
    assert!(sent.iter().all(|c| !c.starts_with("MOV")), "{sent:?}");
    assert_eq!(se.position(), [0.0; 3]);
}

#[test]
fn engine_stage_error_mid_scan_saves_partial_and_stops_commanding_the_stage() {
    let (se, _qe, mut c, limits) = engine_setup();
    c.instrument.stage.move_to([0.2, 0.1, 0.0]).unwrap();
    // settle at once: each move is exactly MOV, #5, ONT? 1, ERR? (`#5` answered the move
    // above; `ONT?` confirms on target; the ERR? follows the end of the trajectory).
    // The engine first sends TMN?, TMX? (the start is the commanded target, known since
    // connect); so the 11th command is the 3rd point's MOV: the controller rejects it, `#5`
    // finds nothing moving, `ONT?` the axis on its old target, and the ERR? reports the error.
    se.faults().settle_s = Some(0.0);
    se.faults().error_after = Some((10, -1024));
    let before = se.commands().len();
    let (r, saved) = run(&mut c.instrument, &line_x(-0.4, 0.4, 5, true), &limits);
    let r = r.unwrap();
    match &r.ended {
        Ended::Failed {
            measured,
            error:
                DeviceError::Controller {
                    command,
                    code,
                    message,
                    ..
                },
            stage_fault,
        } => {
            assert_eq!((*measured, *code, *stage_fault), (2, -1024, true));
            assert_eq!(command, "MOV 1 0.200000"); // start + 0.0, only x moves
            assert!(message.starts_with("Motion error"), "{message}");
        }
        other => panic!("{other:?}"),
    }
    // partial scan saved, status failed, unmeasured pixels NaN
    assert_eq!(saved.len(), 1);
    assert_eq!(saved[0].status, ScanStatus::Failed);
    let row: Vec<f64> = saved[0].sx.data.row(0).to_vec();
    assert!(
        row[..2].iter().all(|v| v.is_finite()) && row[2..].iter().all(|v| v.is_nan()),
        "{row:?}"
    );
    // relative scan, but after a stage fault the stage is not moved again (not even back to
    // the start): after the rejected MOV, its #5 and ERR?, the one command it gets is STP (and the
    // ERR? that reads STP's own code 10)
    assert!(!r.returned_to_start);
    std::thread::sleep(Duration::from_millis(100));
    let sent = se.commands()[before..].to_vec();
    assert_eq!(sent.len(), 16, "{sent:?}");
    assert_eq!(
        &sent[10..],
        ["MOV 1 0.200000", "#5", "ONT? 1", "ERR?", "STP", "ERR?"]
    );
    assert!(r
        .summary()
        .unwrap_err()
        .contains("the stage was not commanded further"));
}

#[test]
fn engine_qpd_unplugged_mid_scan_returns_relative_scan_to_start() {
    let (se, qe, mut c, limits) = engine_setup();
    c.instrument.stage.move_to([0.2, 0.1, 0.0]).unwrap();
    // first read: COUN, ERR?, STAT?; later reads: STAT?: unplug after 3 points
    qe.faults().unplug_after = Some(5);
    let (r, saved) = run(&mut c.instrument, &line_x(-0.4, 0.4, 5, true), &limits);
    let r = r.unwrap();
    match &r.ended {
        Ended::Failed {
            measured: 3,
            error: DeviceError::Disconnected { device, .. },
            stage_fault: false,
        } => {
            assert!(device.contains(qe.path()));
        }
        other => panic!("{other:?}"),
    }
    assert!(r.returned_to_start);
    assert_eq!(se.position(), [0.2, 0.1, 0.0]);
    assert_eq!(saved.len(), 1);
    assert_eq!(saved[0].status, ScanStatus::Failed);
    assert_eq!(saved[0].meta["points_measured"], 3);
}

#[test]
fn engine_speed_limit_holds_on_the_real_drivers_before_anything_is_sent() {
    // settle 0 (config) + dwell 0.1 ms (10 samples at 100 kHz); steps of 0.25 µm → 2500 µm/s
    let (se, _qe, mut c, mut limits) = engine_setup();
    limits.max_speed_um_s = Some(1000.0);
    let before = se.commands().len();
    let (r, saved) = run(&mut c.instrument, &line_x(-0.5, 0.5, 5, false), &limits);
    match r {
        Err(ScanError::Refused(msg)) => assert!(
            msg.contains(
                "from point 1 to point 2 of 5 the stage moves 0.25 µm in settle 0 s + dwell 1.000e-4 s = \
                 1.000e-4 s per point: 2500 µm/s exceeds max_speed_um_s = 1000 µm/s"
            ),
            "{msg}"
        ),
        other => panic!("{:?}", other.map(|r| r.ended)),
    }
    assert!(saved.is_empty());
    let sent = &se.commands()[before..];
    assert!(sent.iter().all(|c| !c.starts_with("MOV")), "{sent:?}");
    // the same line with a dwell of 1 ms: 250 µm/s, runs
    let slow = Plan::line(
        "ascan",
        Sweep::new("ascan", Axis::X, -0.5, 0.5, 5, "n").unwrap(),
        1e-3,
        false,
    )
    .unwrap();
    let (r, _) = run(&mut c.instrument, &slow, &limits);
    let r = r.unwrap();
    assert_eq!(r.ended, Ended::Complete);
    let v = r.scan.meta["max_speed_between_points_um_s"]
        .as_f64()
        .unwrap();
    assert!((v - 250.0).abs() < 1e-9, "{v}");
    assert_eq!(se.position(), [0.5, 0.0, 0.0]);
}

#[test]
fn connect_emulated_scans_the_simulated_scene_through_the_drivers() {
    use bfpscope::config::connect::connect_emulated;
    let mut scene = Scene::default();
    scene
        .add_bead(Bead {
            pos: [0.0; 3],
            d_nm: 110.0,
            n: 1.572,
        })
        .unwrap();
    let core = SimCore::new(&Optics::default(), &scene, SimConfig::default()).unwrap();
    let mut base = Config::from_toml_str(
        "[safety]\nsoft_limits = { x = [-1.0, 1.0] }\n[stage]\nsettle_s = 0.0\n",
        "t",
    )
    .unwrap();
    base.stage.port = Some("/dev/ignored-for-emulators".into());
    let noise_v = 2e-4;
    let mut e = connect_emulated(core.renderer(), &core.cfg, &base, noise_v).unwrap();
    let d = &e.connected.instrument.description;
    assert_eq!(d["backend"], "emulated");
    assert_eq!(d["stage"]["port"], e.stage.path());
    assert_eq!(d["emulators"]["qpd"], e.qpd.path());
    // [safety] of the base config ∩ the simulator's travel range
    assert_eq!(
        e.connected.limits.range,
        [(-1.0, 1.0), (-37.5, 37.5), (-25.0, 25.0)]
    );
    assert_eq!(e.connected.instrument.settle_s, 0.0);
    // one scan on both instruments, through the engine
    let plan = Plan::grid(
        "scan_xy",
        Sweep::new("scan_xy", Axis::X, -0.5, 0.5, 9, "nx").unwrap(),
        Sweep::new("scan_xy", Axis::Y, -0.5, 0.5, 9, "ny").unwrap(),
        vec![],
        1e-3,
        false,
        true,
    )
    .unwrap();
    let limits = e.connected.limits;
    let (hw, _) = run(&mut e.connected.instrument, &plan, &limits);
    let (sim, _) = run(&mut core.instrument(0.0), &plan, &limits);
    let (hw, sim) = (hw.unwrap(), sim.unwrap());
    assert_eq!(
        (hw.ended.clone(), sim.ended.clone()),
        (Ended::Complete, Ended::Complete)
    );
    let sigma = noise_v / 100f64.sqrt(); // 100 samples per point, 1 V per signal unit
    assert!(sim.scan.sx.data.iter().any(|v| v.abs() > 50.0 * sigma));
    let mut chi2 = 0.0;
    for (a, b) in [
        (&hw.scan.sx, &sim.scan.sx),
        (&hw.scan.sy, &sim.scan.sy),
        (&hw.scan.sz, &sim.scan.sz),
    ] {
        assert_eq!(a.x, b.x);
        for (p, q) in a.data.iter().zip(b.data.iter()) {
            assert!((p - q).abs() < 5.0 * sigma, "{p} vs {q} (σ {sigma})");
            chi2 += ((p - q) / sigma).powi(2);
        }
    }
    let dof = 3.0 * 81.0;
    assert!(
        chi2 / dof > 0.6 && chi2 / dof < 1.5,
        "χ²/dof = {}",
        chi2 / dof
    );
    assert_eq!(hw.scan.meta["instrument"]["backend"], "emulated");
    // real time: the first row's cost per point is measured (and the ETA revised from it): at
    // least the 1 ms dwell, at least half the whole scan's mean, and the first row (9 points,
    // one-time costs such as the emulator's first rendering of the scene included) is part of
    // the whole scan
    let t = &hw.scan.meta["time"];
    let per = t["measured_s_per_point_first_row"].as_f64().unwrap();
    let wall = t["wall_s"].as_f64().unwrap();
    let whole = wall / 81.0;
    assert!(
        per >= 1e-3 && per * 9.0 < wall && per > 0.5 * whole,
        "{per} s vs {whole} s per point"
    );
    assert!(sim.scan.meta["time"]["measured_s_per_point_first_row"].is_null());
    // the scan went through the serial protocol
    let cmds = e.stage.commands();
    assert!(
        cmds.iter().filter(|c| c.starts_with("MOV")).count() >= 81,
        "{}",
        cmds.len()
    );
    // one measurement per pixel, of the means the scan stores
    assert_eq!(
        e.qpd
            .commands()
            .iter()
            .filter(|c| *c == "MEAS:QPD?")
            .count(),
        81
    );
    // the ETA of the next scan counts what the first measured beyond settle + dwell: the mean
    // move (link and on-target polling included) and the QPD's reply time
    let move_ms = t["phases"]["move_ms"].as_f64().unwrap();
    assert!(move_ms > 0.0, "{}", t["phases"]);
    let (again, _) = run(&mut e.connected.instrument, &plan, &limits);
    let eta = again.unwrap().scan.meta["time"]["eta_s"].as_f64().unwrap();
    let bare = 81.0 * (0.0 + 1e-3);
    assert!(
        eta - bare >= 0.5 * 81.0 * move_ms * 1e-3,
        "ETA {eta} s: settle + dwell {bare} s and the first scan's moves {move_ms} ms per point"
    );
}

#[test]
fn workbench_connects_to_hardware_ports_and_reconnects_to_the_same_ports() {
    use bfpscope::script::{Settings, Workbench};
    let (se, qe) = pair(0.0);
    let dir = std::env::temp_dir().join(format!("bfpscope-hw-wb-{}", std::process::id()));
    cleanup::at_exit(&dir);
    let (settings, _buf) = Settings::captured(&dir);
    let mut wb = Workbench::new(settings);
    let call = connect_call(&se, &qe);
    let r = wb.eval_source("t", &call).unwrap().to_string();
    assert!(
        r.starts_with("connected hardware: PI E-727 on /dev/"),
        "{r}"
    );
    // again, to the same (exclusively opened) ports: the old connection is closed first
    let r = wb.eval_source("t", &call).unwrap().to_string();
    assert!(r.starts_with("connected hardware"), "{r}");
    let st = wb
        .eval_source(
            "t",
            "mv(#{x: 0.5}); [status().backend, status().instrument.stage.port, pos().x]",
        )
        .unwrap();
    assert_eq!(
        bfpscope::script::show(&st),
        format!("[\"hardware\", \"{}\", 0.5]", se.path())
    );
    assert_eq!(se.position()[0], 0.5);
    // a connect that fails (bad QPD port) after closing the shared stage port leaves nothing
    // half-open: the stage port opens again
    let bad = format!(
        "connect(#{{backend: \"hardware\", stage_port: \"{}\", qpd_port: \"/dev/bfpscope-no-such-qpd\"}})",
        se.path()
    );
    let e = wb.eval_source("t", &bad).unwrap_err();
    assert!(
        e.message.contains(
            "connect: backend = \"hardware\": SCPI QPD on /dev/bfpscope-no-such-qpd: cannot open"
        ),
        "{e}"
    );
    let _s = open_stage(&se, 1000);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn untouched_axes_keep_their_targets_bit_identical_and_relative_moves_add_to_the_target() {
    // A closed-loop piezo reads its sensor with nanometre noise around the
    // target (the emulator's POS? here carries ±2 nm). Moves must name only the axes asked
    // for, and relative moves must add to the last commanded target (PI's MVR), not to a fresh
    // POS?: before the fix, `mvr(#{x: 0.5, y: -0.25})` re-commanded z from POS? and 50 relative
    // moves of 0.1 µm accumulated the sensor noise into x's target.
    let stage = StageEmulatorConfig {
        travel: [(0.0, 100.0), (0.0, 100.0), (0.0, 20.0)],
        settle_s: 0.0005,
        ..Default::default()
    };
    let (se, qe) = start_pair(stage, qpd_cfg(0.0), standin_bead).unwrap();
    se.faults().pos_noise_um = 0.002;
    let mut wb = workbench_on(&se, &qe, "mvr");
    let _ = wb.eval_source("t", "mv(#{x: 40, y: 45, z: 10})").unwrap();
    // the sensor really is noisy: POS? is not the target
    let p = wb.eval_source("t", "pos().x").unwrap().as_float().unwrap();
    assert!(p != 40.0 && (p - 40.0).abs() <= 0.002, "{p}");
    let before = se.commands().len();
    let _ = wb.eval_source("t", "mvr(#{x: 0.5, y: -0.25})").unwrap();
    let movs: Vec<String> = se.commands()[before..]
        .iter()
        .filter(|c| c.starts_with("MOV "))
        .cloned()
        .collect();
    assert_eq!(
        movs,
        ["MOV 1 40.500000 2 44.750000"],
        "z was not asked to move"
    );
    let before = se.commands().len();
    let _ = wb
        .eval_source("t", "mv(#{x: 40}); for i in 0..50 { mvr(#{x: 0.1}) }")
        .unwrap();
    let sent = se.commands()[before..].to_vec();
    assert!(
        sent.iter()
            .filter(|c| c.starts_with("MOV "))
            .all(|c| c.starts_with("MOV 1 ") && !c.contains(" 2 ") && !c.contains(" 3 ")),
        "only x is commanded: {sent:?}"
    );
    assert_eq!(sent.iter().filter(|c| c.starts_with("MOV ")).count(), 51);
    // x's target: 40 + 50 × 0.1 = 45.000000 as sent (f64 sums to 44.99999999999998, which the
    // 6-decimal command rounds to 45.000000); y and z: exactly what was commanded
    drop(wb); // release the port, then ask the controller itself (MOV? at connect)
    let mut s = GcsStage::open(se.path(), BAUD, opts(1000, 2000)).unwrap();
    let t = s.commanded_target().unwrap();
    assert_eq!(t, [45.0, 44.75, 10.0]);
    for (i, want) in [45.0f64, 44.75, 10.0].iter().enumerate() {
        assert_eq!(t[i].to_bits(), want.to_bits(), "axis {i}");
    }
}

#[test]
fn engine_on_target_timeout_mid_scan_sends_stp_and_saves_the_partial_scan() {
    // When the on-target wait times out the axis may still be moving; the one
    // command the stage then gets is STP (PI's stop: all axes, error 10 afterwards), the partial
    // scan is saved as failed, and nothing moves it back to the start.
    let (se, qe) = pair(0.0);
    let text = emulator_config_text(&se, &qe)
        .replace("on_target_timeout_ms = 2000", "on_target_timeout_ms = 150");
    let cfg = Config::from_toml_str(&text, "test.toml").unwrap();
    let mut c = connect(&cfg, no_sim).unwrap();
    let limits = cfg.soft_limits();
    se.faults().settle_s = Some(30.0);
    let before = se.commands().len();
    let (r, saved) = run(&mut c.instrument, &line_x(-0.4, 0.4, 5, true), &limits);
    let r = r.unwrap();
    match &r.ended {
        Ended::Failed {
            measured,
            error: DeviceError::Other { detail, .. },
            stage_fault,
        } => {
            assert_eq!((*measured, *stage_fault), (0, true));
            assert!(
                detail.starts_with("not on target within 150 ms"),
                "{detail}"
            );
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(saved.len(), 1);
    assert_eq!(saved[0].status, ScanStatus::Failed);
    std::thread::sleep(Duration::from_millis(50));
    let sent = se.commands()[before..].to_vec();
    let stp = sent.iter().position(|c| c == "STP").expect("STP sent");
    assert!(
        sent[stp + 1..].iter().all(|c| !c.starts_with("MOV")),
        "no motion after the stop: {sent:?}"
    );
    assert_eq!(
        sent.iter().filter(|c| c.starts_with("MOV ")).count(),
        1,
        "{sent:?}"
    );
}

#[test]
fn servo_trip_mid_move_is_reported_as_minus_1024_with_its_text_then_stopped() {
    // A servo trip (−1024) is an asynchronous error: the MOV was accepted,
    // then the axis stops, servo off, never on target. Polling ERR? with ONT? reports it as
    // itself within ERR_POLL_EVERY polls, not as an on-target timeout seconds later (the
    // on-target timeout here is 2 s), and the engine then sends the stop.
    let (se, qe) = pair(0.0);
    let cfg = emulator_config(&se, &qe);
    let mut c = connect(&cfg, no_sim).unwrap();
    let limits = cfg.soft_limits();
    se.faults().settle_s = Some(0.05);
    se.faults().servo_trip_next_move = true;
    let before = se.commands().len();
    let t0 = Instant::now();
    let (r, saved) = run(&mut c.instrument, &line_x(-0.4, 0.4, 5, false), &limits);
    assert!(
        t0.elapsed() < Duration::from_millis(1000),
        "{:?}",
        t0.elapsed()
    );
    match &r.unwrap().ended {
        Ended::Failed {
            measured: 0,
            error:
                DeviceError::Controller {
                    command,
                    code: -1024,
                    message,
                    ..
                },
            stage_fault: true,
        } => {
            assert_eq!(command, "MOV 1 -0.400000");
            assert_eq!(
                message,
                "Motion error: position error too large, servo is switched off automatically"
            );
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(saved[0].status, ScanStatus::Failed);
    let sent = se.commands()[before..].to_vec();
    let onts = sent.iter().filter(|c| c.starts_with("ONT?")).count();
    assert!(
        onts <= bfpscope::instrument::gcs::ERR_POLL_EVERY,
        "{sent:?}"
    );
    assert_eq!(&sent[sent.len() - 2..], ["STP", "ERR?"], "{sent:?}");
}

#[test]
fn gcs_query_sends_queries_only() {
    // Raw access for debugging, queries only; a motion command is refused
    // before anything reaches the port.
    let (se, qe) = pair(0.0);
    let mut wb = workbench_on(&se, &qe, "gq");
    let r = wb.eval_source("t", "gcs_query(\"MOV? 1 2\")").unwrap();
    assert_eq!(
        bfpscope::script::show(&r),
        "[\"1=0.000000\", \"2=0.000000\"]"
    );
    let before = se.commands().len();
    for bad in ["MOV 1 1", "SVO 1 0", "STP", "POS?; MOV 1 1"] {
        let e = wb
            .eval_source("t", &format!("gcs_query(\"{bad}\")"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("is not a query"), "{bad}: {e}");
    }
    assert_eq!(se.commands().len(), before, "nothing was sent");
    // an unknown query is the controller's own error 2, named
    let e = wb
        .eval_source("t", "gcs_query(\"XYZ?\")")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("controller error 2") && e.contains("XYZ?"),
        "{e}"
    );
}

#[test]
fn safety_speed_limit_is_sent_as_vel_at_connect_and_read_back_in_status() {
    // Positioning moves respect the [safety] speed limit too: connect sends
    // it as VEL (µm/s × units_per_um), and status() reports the controller's VEL?.
    use bfpscope::script::{Settings, Workbench};
    let (se, qe) = pair(0.0);
    let text = emulator_config_text(&se, &qe).replace(
        "max_step_um = 2.0",
        "max_step_um = 2.0\nmax_speed_um_s = 250.0",
    );
    let dir = std::env::temp_dir().join(format!("bfpscope-hw-vel-{}", std::process::id()));
    cleanup::at_exit(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let cfg = Config::from_toml_str(&text, "test.toml").unwrap();
    let (mut settings, _buf) = Settings::captured(&dir);
    settings.apply_config(cfg, None).unwrap();
    let mut wb = Workbench::new(settings);
    let _ = wb.eval_source("t", "connect()").unwrap();
    assert!(
        se.commands()
            .contains(&"VEL 1 250.000000 2 250.000000 3 250.000000".to_string()),
        "{:?}",
        se.commands()
    );
    let v = wb.eval_source("t", "status().velocity_um_s").unwrap();
    assert_eq!(
        bfpscope::script::show(&v),
        "#{x_um_s: 250.0, y_um_s: 250.0, z_um_s: 250.0}"
    );
}

/// A workbench connected to the emulator pair through the `connect` binding.
fn workbench_on(se: &Emulator, qe: &Emulator, tag: &str) -> bfpscope::script::Workbench {
    use bfpscope::script::{Settings, Workbench};
    let dir = std::env::temp_dir().join(format!("bfpscope-hw-{tag}-{}", std::process::id()));
    cleanup::at_exit(&dir);
    let (settings, _buf) = Settings::captured(&dir);
    let mut wb = Workbench::new(settings);
    let _ = wb.eval_source("t", &connect_call(se, qe)).unwrap();
    wb
}

/// The `connect` call for the emulator pair.
fn connect_call(se: &Emulator, qe: &Emulator) -> String {
    format!(
        "connect(#{{backend: \"hardware\", stage_port: \"{}\", qpd_port: \"{}\", timeout_ms: 1000}})",
        se.path(),
        qe.path()
    )
}

// ---------------------------------------------------------------------------------------------
// Connect like PI's own software (SAI?, SVO?, TMN?/TMX? before SVO), one
// axis per query, stages split across controllers

#[test]
fn connect_reads_sai_svo_and_the_travel_range_before_switching_servos_on() {
    let (se, qe) = pair(0.0);
    let cfg = emulator_config(&se, &qe);
    let c = connect(&cfg, no_sim).unwrap();
    assert_eq!(
        se.commands(),
        [
            "*IDN?",
            "ERR?",
            "SAI?",
            "SVO? 1 2 3",
            "MOV? 1 2 3",
            "TMN? 1 2 3",
            "TMX? 1 2 3",
            "SVO 1 1 2 1 3 1",
            "ERR?"
        ]
    );
    let ctl = &c.instrument.description["stage"]["controllers"][0];
    assert_eq!(ctl["sai"], serde_json::json!(["1", "2", "3"]));
    assert_eq!(
        ctl["servo_at_connect"],
        serde_json::json!({"x": false, "y": false, "z": false})
    );
    assert_eq!(ctl["one_axis_per_query"], false);
}

#[test]
fn connect_refused_for_its_limits_leaves_the_servos_as_found() {
    // y's soft limits [5, 9] do not overlap the travel [-2, 2]: the connect is refused after
    // TMN?/TMX? and before any SVO, so the servos stay off (as the emulator powers up).
    let (se, qe) = pair(0.0);
    se.faults().settle_s = Some(0.0);
    let mut cfg = emulator_config(&se, &qe);
    cfg.safety.soft_limits.y = Some([5.0, 9.0]);
    let e = connect(&cfg, no_sim).err().expect("refused");
    assert_eq!(
        e.to_string(),
        "bfpscope.toml: safety.soft_limits.y: safety.soft_limits.y = [5, 9] µm does not overlap \
         the stage's travel range [-2, 2] µm"
    );
    let sent = se.commands();
    assert_eq!(
        sent.last().map(String::as_str),
        Some("TMX? 1 2 3"),
        "{sent:?}"
    );
    assert!(
        sent.iter()
            .all(|c| !c.starts_with("SVO ") && !c.starts_with("VEL ")),
        "{sent:?}"
    );
    // ask the controller itself, on a fresh connection that switches nothing on
    let mut s = GcsStage::open_checked(se.path(), BAUD, opts(1000, 2000)).unwrap();
    assert_eq!(s.query_only("SVO?").unwrap(), ["1=0", "2=0", "3=0"]);
    assert_eq!(s.servo_at_connect(), [Some(false); 3]);
}

#[test]
fn connect_switches_on_only_the_servos_found_off() {
    let stage = StageEmulatorConfig {
        travel: [(-2.0, 2.0), (-2.0, 2.0), (-1.0, 1.0)],
        servo_on: true,
        ..Default::default()
    };
    let (se, qe) = start_pair(stage, qpd_cfg(0.0), standin_bead).unwrap();
    let cfg = emulator_config(&se, &qe);
    let mut c = connect(&cfg, no_sim).unwrap();
    assert!(
        se.commands().iter().all(|c| !c.starts_with("SVO ")),
        "{:?}",
        se.commands()
    );
    c.instrument.stage.move_to([0.5, 0.0, 0.0]).unwrap();
    assert_eq!(se.position(), [0.5, 0.0, 0.0]);
}

#[test]
fn connect_with_axes_the_controller_lacks_names_device_axes_and_sai_reply() {
    let stage = StageEmulatorConfig {
        inactive_axes: vec!["4".into()],
        ..Default::default()
    };
    let (se, qe) = start_pair(stage, qpd_cfg(0.0), standin_bead).unwrap();
    let text = emulator_config_text(&se, &qe).replace(
        "poll_ms = 1",
        "poll_ms = 1\naxes = { x = \"1\", y = \"2\", z = \"4\" }",
    );
    let cfg = Config::from_toml_str(&text, "test.toml").unwrap();
    let e = connect(&cfg, no_sim).err().expect("refused");
    assert_eq!(
        e.to_string(),
        format!(
            "PI E-727 on {}: configured axes x = \"1\", y = \"2\", z = \"4\" are not all axes of this \
             controller: `SAI?` answered 1 2 3 (`SAI? ALL`, deactivated axes too: 1 2 3 4); 4 missing. \
             Set [stage] axes in bfpscope.toml to the controller's identifiers, e.g. axes = {{ x = \"1\", \
             y = \"2\", z = \"3\" }}",
            se.path()
        )
    );
    assert_eq!(se.commands(), ["*IDN?", "ERR?", "SAI?", "SAI? ALL"]);
}

#[test]
fn emulator_answers_sai_and_sai_all_as_pi_documents() {
    let cfg = StageEmulatorConfig {
        inactive_axes: vec!["4".into()],
        ..Default::default()
    };
    let emu = start_stage_emulator(cfg, shared_position([0.0; 3])).unwrap();
    let mut s = open_stage(&emu, 200);
    // one identifier per line, every line but the last ending in a space
    assert_eq!(s.query_lines("SAI?").unwrap(), ["1", "2", "3"]);
    assert_eq!(s.query_lines("SAI? ALL").unwrap(), ["1", "2", "3", "4"]);
    assert_eq!(s.query_lines("sai? all").unwrap(), ["1", "2", "3", "4"]);
    match s.query_lines("SAI? 1") {
        Err(DeviceError::Controller {
            code: 1, command, ..
        }) => assert_eq!(command, "SAI? 1"),
        other => panic!("{other:?}"),
    }
}

/// A stage emulator that answers one axis per query.
fn one_axis_emu() -> Emulator {
    let cfg = StageEmulatorConfig {
        travel: [(-50.0, 50.0), (-40.0, 60.0), (0.0, 20.0)],
        settle_s: 0.005,
        one_axis_per_query: true,
        ..StageEmulatorConfig::default()
    };
    start_stage_emulator(cfg, shared_position([0.0; 3])).unwrap()
}

#[test]
fn one_axis_per_query_controller_is_detected_and_asked_axis_by_axis() {
    let emu = one_axis_emu();
    let mut s = open_stage(&emu, 1000);
    assert!(s.one_axis_per_query());
    // the emulated controller really answers the first axis only
    assert_eq!(s.query_only("POS? 1 2 3").unwrap(), ["1=0.000000"]);
    assert_eq!(
        emu.commands()[..11],
        [
            "*IDN?",
            "ERR?",
            "SAI?",
            "SVO? 1 2 3",
            "SVO? 2",
            "SVO? 3",
            "MOV? 1",
            "MOV? 2",
            "MOV? 3",
            "SVO 1 1 2 1 3 1",
            "ERR?"
        ]
    );
    let before = emu.commands().len();
    s.move_to([1.5, -2.5, 3.5]).unwrap();
    assert_eq!(s.position().unwrap(), [1.5, -2.5, 3.5]);
    assert_eq!(s.travel_range().unwrap()[1], (-40.0, 60.0));
    let sent = emu.commands()[before..].to_vec();
    assert_eq!(sent[..2], ["MOV 1 1.500000 2 -2.500000 3 3.500000", "ERR?"]);
    // the end of the move is polled with `#5`: one byte, whatever the axes
    assert!(sent.contains(&"#5".to_string()), "{sent:?}");
    assert!(
        sent.iter()
            .filter(|c| c.ends_with('?') || c.contains("? "))
            .all(|c| c.split_whitespace().count() <= 2),
        "a query named several axes: {sent:?}"
    );
    let n = sent.len();
    assert_eq!(sent[n - 9..n - 6], ["POS? 1", "POS? 2", "POS? 3"]);
    // with `ONT?` polling, axis by axis, an on-target timeout names the last per-axis query
    emu.faults().settle_s = Some(30.0);
    drop(s);
    let o = GcsOptions {
        motion_status: false,
        ..opts(200, 200)
    };
    let mut s = GcsStage::open(emu.path(), BAUD, o).unwrap();
    let e = s.move_to([20.0, -2.5, 3.5]).unwrap_err().to_string();
    assert!(e.ends_with("(last `ONT? 3` reply: 1=0 2=1 3=1)"), "{e}");
}

#[test]
fn one_axis_per_query_can_be_configured() {
    let emu = one_axis_emu();
    let o = GcsOptions {
        one_axis_per_query: true,
        ..opts(1000, 2000)
    };
    let mut s = GcsStage::open(emu.path(), BAUD, o).unwrap();
    assert_eq!(emu.commands()[3..6], ["SVO? 1", "SVO? 2", "SVO? 3"]);
    s.move_to([1.0, 2.0, 3.0]).unwrap();
    assert_eq!(s.position().unwrap(), [1.0, 2.0, 3.0]);
}

/// Two emulated controllers: XY on an E-727 (pseudo-terminal), Z on an E-709 served over TCP
/// (its axis 1; the emulator has three channels, only axis 1 is configured), and a QPD.
fn split_setup() -> (Emulator, Emulator, Emulator, Config) {
    let xy = StageEmulatorConfig {
        travel: [(-2.0, 2.0), (-2.0, 2.0), (0.0, 1.0)],
        settle_s: 0.001,
        ..Default::default()
    };
    let z = StageEmulatorConfig {
        travel: [(-1.0, 1.0), (0.0, 1.0), (0.0, 1.0)],
        settle_s: 0.001,
        idn: "(c)2026 Physik Instrumente (PI) GmbH & Co. KG, E-709, 0000000001, 1.0.0 (bfpscope emulator)"
            .into(),
        ..Default::default()
    };
    let sxy = start_stage_emulator(xy, shared_position([0.0; 3])).unwrap();
    let sz = bfpscope::instrument::emulator::start_stage_emulator_tcp(
        z,
        shared_position([0.0; 3]),
        "127.0.0.1:0",
    )
    .unwrap();
    let qe = qpd_emu(0.0, [0.0; 3]);
    let text = format!(
        r#"
[stage]
backend = "gcs"
ports = {{ x = "{xy}", y = "{xy}", z = "{z}" }}
axes = {{ x = "1", y = "2", z = "1" }}
timeout_ms = 500
on_target_timeout_ms = 2000
poll_ms = 1
settle_s = 0.0

[qpd]
backend = "scpi"
port = "{q}"
"#,
        xy = sxy.path(),
        z = sz.path(),
        q = qe.path()
    );
    let cfg = Config::from_toml_str(&text, "split.toml").unwrap();
    (sxy, sz, qe, cfg)
}

#[test]
fn stage_split_across_two_controllers_moves_each_its_own_axes() {
    let (sxy, sz, _qe, cfg) = split_setup();
    assert!(sz.path().starts_with("tcp://127.0.0.1:"), "{}", sz.path());
    let mut c = connect(&cfg, no_sim).unwrap();
    let stage = &mut c.instrument.stage;
    assert_eq!(
        stage.name(),
        format!(
            "PI E-727 on {} (x, y) + PI E-709 on {} (z)",
            sxy.path(),
            sz.path()
        )
    );
    // each controller is checked and switched on for its own axes only
    assert_eq!(
        sxy.commands(),
        [
            "*IDN?",
            "ERR?",
            "SAI?",
            "SVO? 1 2",
            "MOV? 1 2",
            "TMN? 1 2",
            "TMX? 1 2",
            "SVO 1 1 2 1",
            "ERR?"
        ]
    );
    assert_eq!(
        sz.commands(),
        ["*IDN?", "ERR?", "SAI?", "SVO? 1", "MOV? 1", "TMN? 1", "TMX? 1", "SVO 1 1", "ERR?"]
    );
    assert_eq!(c.limits.range, [(-2.0, 2.0), (-2.0, 2.0), (-1.0, 1.0)]);
    let (nxy, nz) = (sxy.commands().len(), sz.commands().len());
    stage.move_to([0.5, -0.25, 0.75]).unwrap();
    assert_eq!(
        sxy.commands()[nxy..nxy + 2],
        ["MOV 1 0.500000 2 -0.250000", "ERR?"]
    );
    assert_eq!(sz.commands()[nz..nz + 2], ["MOV 1 0.750000", "ERR?"]);
    assert_eq!(stage.position().unwrap(), [0.5, -0.25, 0.75]);
    assert_eq!(sxy.position(), [0.5, -0.25, 0.0]);
    assert_eq!(sz.position(), [0.75, 0.0, 0.0]);
    // a move of z alone talks to the E-709 only
    let nxy = sxy.commands().len();
    stage.move_to([0.5, -0.25, 0.5]).unwrap();
    assert_eq!(sxy.commands().len(), nxy, "{:?}", &sxy.commands()[nxy..]);
    assert_eq!(stage.target().unwrap(), [0.5, -0.25, 0.5]);
    let d = &c.instrument.description["stage"];
    assert_eq!(d["port"]["z"], sz.path());
    assert_eq!(d["controllers"][1]["axes"], serde_json::json!({"z": "1"}));
}

#[test]
fn stage_split_fault_on_one_controller_stops_all_of_them() {
    use bfpscope::acquire::checked_move;
    let (sxy, sz, _qe, cfg) = split_setup();
    let mut c = connect(&cfg, no_sim).unwrap();
    // TMN? 1 and TMX? 1 (checked_move reads the travel range) pass, the MOV is rejected
    sz.faults().error_after = Some((2, 7));
    let (nxy, nz) = (sxy.commands().len(), sz.commands().len());
    let e = checked_move(
        &mut c.instrument,
        &c.limits,
        [0.5, 0.5, 0.5],
        "mv",
        &AtomicBool::new(false),
    )
    .unwrap_err();
    assert_eq!(
        e,
        format!(
            "mv: PI E-709 on {}: controller error 7 after `MOV 1 0.500000`: Position out of limits; \
             the stage was stopped",
            sz.path()
        )
    );
    // the E-727 got its MOV first (the axes move together), then both got STP and nothing after
    let sent_xy = sxy.commands()[nxy..].to_vec();
    let sent_z = sz.commands()[nz..].to_vec();
    assert_eq!(
        &sent_xy[sent_xy.len() - 2..],
        ["STP", "ERR?"],
        "{sent_xy:?}"
    );
    assert_eq!(&sent_z[sent_z.len() - 2..], ["STP", "ERR?"], "{sent_z:?}");
    assert!(sent_z.contains(&"MOV 1 0.500000".to_string()));
}

#[test]
fn stage_split_ports_that_do_not_open_close_the_ones_opened() {
    let (sxy, sz, _qe, cfg) = split_setup();
    let text = cfg.to_toml().replace(sz.path(), "tcp://127.0.0.1:1");
    let cfg = Config::from_toml_str(&text, "split.toml").unwrap();
    let e = connect(&cfg, no_sim).err().expect("must fail").to_string();
    assert!(
        e.starts_with("GCS stage on tcp://127.0.0.1:1: cannot connect to tcp://127.0.0.1:1:"),
        "{e}"
    );
    // the E-727 was only read, and its port is free again
    assert!(sxy.commands().iter().all(|c| !c.starts_with("SVO ")));
    let _s = open_stage(&sxy, 1000);
}

// ---------------------------------------------------------------------------------------------
// GCS over TCP (PI controllers' port 50000), here on loopback

fn tcp_stage_emu() -> Emulator {
    let cfg = StageEmulatorConfig {
        travel: [(-50.0, 50.0), (-40.0, 60.0), (0.0, 20.0)],
        settle_s: 0.005,
        ..StageEmulatorConfig::default()
    };
    bfpscope::instrument::emulator::start_stage_emulator_tcp(
        cfg,
        shared_position([0.0; 3]),
        "127.0.0.1:0",
    )
    .unwrap()
}

#[test]
fn tcp_connect_move_fault_stop_over_loopback() {
    let emu = tcp_stage_emu();
    let url = emu.path().to_string();
    assert!(url.starts_with("tcp://127.0.0.1:"), "{url}");
    let mut s = GcsStage::open(&url, BAUD, opts(200, 2000)).unwrap();
    assert_eq!(s.name(), format!("PI E-727 on {url}"));
    assert_eq!(emu.commands()[..3], ["*IDN?", "ERR?", "SAI?"]);
    // move
    s.move_to([12.5, -33.25, 7.125]).unwrap();
    assert_eq!(s.position().unwrap(), [12.5, -33.25, 7.125]);
    assert!(emu
        .commands()
        .contains(&"MOV 1 12.500000 2 -33.250000 3 7.125000".to_string()));
    // controller error, named
    emu.faults().error_next = Some(7);
    match s.move_to([1.0, 2.0, 3.0]) {
        Err(DeviceError::Controller {
            device,
            command,
            code,
            message,
        }) => {
            assert_eq!(device, format!("PI E-727 on {url}"));
            assert_eq!(command, "MOV 1 1.000000 2 2.000000 3 3.000000");
            assert_eq!((code, message.as_str()), (7, "Position out of limits"));
        }
        other => panic!("{other:?}"),
    }
    // no reply: a timeout within the reply timeout, naming the query
    emu.faults().silent = true;
    let t0 = Instant::now();
    match s.position() {
        Err(DeviceError::Timeout {
            command,
            timeout_ms,
            ..
        }) => assert_eq!((command.as_str(), timeout_ms), ("POS? 1 2 3", 200)),
        other => panic!("{other:?}"),
    }
    assert_bounded(t0, 1.5);
    emu.faults().silent = false;
    // garbled, then resynchronised
    emu.faults().garble_replies = 1;
    assert!(matches!(s.position(), Err(DeviceError::Garbled { .. })));
    assert_eq!(s.position().unwrap(), [12.5, -33.25, 7.125]);
    // stop mid-move: STP, the axis stays where it stopped
    emu.faults().settle_s = Some(2.0);
    s.move_no_wait([40.0, -33.25, 7.125]).unwrap();
    std::thread::sleep(Duration::from_millis(100));
    s.stop().unwrap();
    let p1 = s.position().unwrap();
    assert!(p1[0] > 12.5 && p1[0] < 40.0, "{p1:?}");
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(s.position().unwrap(), p1, "still moving after STP");
    let log = emu.commands();
    let stp = log.iter().rposition(|c| c == "STP").expect("STP sent");
    assert_eq!(log[stp + 1], "ERR?");
    // a second client after the first leaves
    drop(s);
    let mut s2 = GcsStage::open(&url, BAUD, opts(1000, 2000)).unwrap();
    assert_eq!(s2.commanded_target().unwrap(), p1);
    // unplugged after the next command (its reply is delivered): then disconnected, bounded
    emu.faults().unplug_after = Some(1);
    assert_eq!(s2.position(), Ok(p1));
    std::thread::sleep(Duration::from_millis(100));
    let t0 = Instant::now();
    match s2.position() {
        Err(DeviceError::Disconnected {
            device, command, ..
        }) => assert_eq!(
            (device, command),
            (format!("PI E-727 on {url}"), "POS? 1 2 3".to_string())
        ),
        other => panic!("{other:?}"),
    }
    assert_bounded(t0, 2.0);
}

#[test]
fn tcp_port_in_the_config_connects_and_a_dead_port_is_named() {
    let se = tcp_stage_emu();
    let qe = qpd_emu(0.0, [0.0; 3]);
    let mut cfg = Config::default();
    cfg.stage.backend = GCS;
    cfg.stage.port = Some(se.path().into());
    cfg.qpd.backend = SCPI;
    cfg.qpd.port = Some(qe.path().into());
    let mut c = connect(&cfg, no_sim).unwrap();
    assert_eq!(c.instrument.description["stage"]["port"], se.path());
    c.instrument.stage.move_to([1.0, 2.0, 3.0]).unwrap();
    assert_eq!(se.position(), [1.0, 2.0, 3.0]);
    drop(c);
    cfg.stage.port = Some("tcp://127.0.0.1:1".into());
    let e = connect(&cfg, no_sim).err().expect("must fail").to_string();
    assert!(
        e.starts_with("GCS stage on tcp://127.0.0.1:1: cannot connect to tcp://127.0.0.1:1: ")
            && e.ends_with("PI controllers listen on 50000)"),
        "{e}"
    );
}

// ---------------------------------------------------------------------------------------------
// Ctrl-C during a single move's on-target wait: STP

#[test]
fn ctrl_c_during_a_single_move_sends_stp() {
    let (se, qe) = pair(0.0);
    let mut wb = workbench_on(&se, &qe, "ctrlc");
    se.faults().settle_s = Some(30.0); // the move would take 30 s
    let abort = wb.ctx.settings.abort.clone();
    let raiser = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(300));
        abort.store(true, Ordering::SeqCst);
    });
    let before = se.commands().len();
    let t0 = Instant::now();
    let e = wb
        .eval_source("t", "mv(#{x: 1.5})")
        .unwrap_err()
        .to_string();
    raiser.join().unwrap();
    assert_bounded(t0, 1.5);
    assert!(
        e.contains(&format!(
            "mv interrupted (Ctrl-C) before PI E-727 on {} was on target; the stage was stopped",
            se.path()
        )),
        "{e}"
    );
    std::thread::sleep(Duration::from_millis(50));
    let sent = se.commands()[before..].to_vec();
    assert_eq!(sent[..2], ["TMN? 1 2 3", "TMX? 1 2 3"], "{sent:?}");
    assert_eq!(sent[2..4], ["MOV 1 1.500000", "ERR?"], "{sent:?}");
    assert_eq!(&sent[sent.len() - 2..], ["STP", "ERR?"], "{sent:?}");
    assert!(
        sent[4..sent.len() - 2]
            .iter()
            .all(|c| c == "#5" || c == "ERR?"),
        "{sent:?}"
    );
    // stopped on the way, not at the target, and not moving any more
    let p = se.position();
    assert!(p[0] > 0.0 && p[0] < 1.5, "{p:?}");
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(se.position(), p);
}

// ---- motion polled with `#5`, per-phase timing, the link model ----

#[test]
fn motion_is_polled_with_the_single_byte_5_and_a_garbled_reply_stops_the_scan() {
    let (se, _qe, mut c, limits) = engine_setup();
    c.instrument.stage.move_to([0.2, 0.1, 0.0]).unwrap();
    // every move of the scan: MOV, #5 (until the trajectory is over), then `ONT? 1` (the moved
    // axis, until on target: once here, the emulator settles at once), ERR?; no POS?
    let before = se.commands().len();
    let (r, _) = run(&mut c.instrument, &line_x(-0.4, 0.4, 5, false), &limits);
    assert_eq!(r.unwrap().ended, Ended::Complete);
    let sent = se.commands()[before..].to_vec();
    assert!(sent.iter().all(|c| !c.starts_with("POS?")), "{sent:?}");
    assert_eq!(
        sent.iter().filter(|c| c.starts_with("ONT?")).count(),
        5,
        "{sent:?}"
    );
    assert!(sent
        .iter()
        .filter(|c| c.starts_with("ONT?"))
        .all(|c| c == "ONT? 1"));
    assert_eq!(sent.iter().filter(|c| c.starts_with("MOV ")).count(), 5);
    assert_eq!(sent.iter().filter(|c| *c == "ERR?").count(), 5);
    // a garbled `#5` reply mid-scan: a stage fault naming `#5` and the reply, then STP only.
    // Settling at once, the scan sends TMN?, TMX?, then per point MOV, #5, ONT? 1, ERR?: the
    // 8th command is the 2nd point's #5.
    se.faults().settle_s = Some(0.0);
    se.faults().garble_after = Some(7);
    let before = se.commands().len();
    let (r, saved) = run(&mut c.instrument, &line_x(-0.4, 0.4, 5, false), &limits);
    let r = r.unwrap();
    match &r.ended {
        Ended::Failed {
            error:
                DeviceError::Garbled {
                    device,
                    command,
                    reply,
                },
            stage_fault: true,
            measured: 1,
        } => {
            assert!(device.contains(se.path()), "{device}");
            assert_eq!(command, "#5");
            assert_eq!(reply, "\u{fffd}#");
        }
        other => panic!("{other:?}"),
    }
    assert!(r.summary().unwrap_err().contains("garbled reply to `#5`"));
    assert_eq!(saved[0].status, ScanStatus::Failed);
    std::thread::sleep(Duration::from_millis(50));
    let sent = se.commands()[before..].to_vec();
    assert_eq!(sent.len(), 10, "{sent:?}");
    assert_eq!(
        &sent[6..],
        ["MOV 1 -0.200000", "#5", "STP", "ERR?"],
        "{sent:?}"
    );
}

#[test]
fn a_controller_without_5_is_polled_with_ont() {
    let cfg = StageEmulatorConfig {
        travel: [(-50.0, 50.0), (-40.0, 60.0), (0.0, 20.0)],
        settle_s: 0.01,
        single_char_commands: false,
        ..StageEmulatorConfig::default()
    };
    let emu = start_stage_emulator(cfg, shared_position([0.0; 3])).unwrap();
    let mut s = GcsStage::open(emu.path(), BAUD, opts(200, 2000)).unwrap();
    assert_eq!(s.motion_query(), None);
    s.move_to([1.0, 0.0, 0.0]).unwrap();
    assert_eq!(s.motion_query(), Some("ONT?"));
    s.move_to([2.0, 0.0, 0.0]).unwrap();
    assert_eq!(s.position().unwrap(), [2.0, 0.0, 0.0]);
    let sent = emu.commands();
    let i = sent.iter().position(|c| c == "#5").unwrap();
    // the refused `#5` (error 2, no reply) is asked once; ERR? explains it; then ONT?
    assert_eq!(sent[i + 1], "ERR?");
    assert_eq!(sent.iter().filter(|c| *c == "#5").count(), 1);
    assert!(
        sent[i + 2..].contains(&"ONT? 1 2 3".to_string()),
        "{sent:?}"
    );
    assert!(sent.contains(&"MOV 1 2.000000".to_string()));
}

#[test]
fn a_scan_on_the_emulators_records_where_its_time_went() {
    let (_se, _qe, mut c, limits) = engine_setup();
    c.instrument.stage.move_to([0.2, 0.1, 0.0]).unwrap();
    let (r, _) = run(&mut c.instrument, &line_x(-0.4, 0.4, 5, false), &limits);
    let r = r.unwrap();
    let p = &r.scan.meta["time"]["phases"];
    assert_eq!(p["points"], 5);
    let f = |k: &str| p[k].as_f64().unwrap();
    // the phases and the rest add up to the time per point
    let sum = f("move_ms") + f("settle_ms") + f("qpd_ms") + f("other_ms");
    assert!((sum - f("per_point_ms")).abs() < 1e-9, "{p}");
    assert_eq!(f("dwell_ms"), 1e-4 * 1e3); // 10 samples at 100 kHz
                                           // per point: one MOV, its ERR?, at least one #5; one measurement and no SYST:ERR?
    let stage = &p["stage_link"];
    assert_eq!(stage["MOV"]["per_point"], 1.0);
    assert_eq!(stage["ERR?"]["per_point"], 1.0);
    assert!(stage["#5"]["per_point"].as_f64().unwrap() >= 1.0, "{p}");
    // one `ONT? 1` per point confirms the end of the move: 7 bytes out, "1=1\n" back
    assert_eq!(stage["ONT?"]["per_point"], 1.0, "{p}");
    assert_eq!(stage["ONT?"]["bytes_per_point"], 11.0, "{p}");
    assert!(stage.get("POS?").is_none(), "{p}");
    // the averaging count is set once (with its SYST:ERR?), for the first of the 5 points
    let qpd = &p["qpd_link"];
    // (the means only: `MEAS:QPD?`, though `statistics` is on for `qpd()` readings)
    assert_eq!(qpd["MEAS:QPD?"]["per_point"], 1.0);
    assert!(qpd.get("MEAS:QPD:STAT?").is_none(), "{p}");
    assert_eq!(qpd["SYST:ERR?"]["per_point"], 0.2);
    // bytes: "MOV 1 -0.400000\n" is 16 (twice), "MOV 1 0.000000\n" 15 (three times);
    // "ERR?\n" + "0\n" 7; 0x05 + "0\n" 3 per #5
    assert_eq!(stage["ERR?"]["bytes_per_point"], 7.0);
    assert_eq!(stage["MOV"]["bytes_per_point"], 15.4);
    assert_eq!(
        stage["#5"]["bytes_per_point"].as_f64().unwrap(),
        3.0 * stage["#5"]["per_point"].as_f64().unwrap()
    );
}

#[test]
fn emulate_link_settings_are_checked() {
    use bfpscope::instrument::emulator::{parse_link, LinkModel};
    assert_eq!(parse_link("max", 0.0).unwrap(), LinkModel::FULL_SPEED);
    assert_eq!(parse_link("0", 0.0).unwrap(), LinkModel::FULL_SPEED);
    assert_eq!(
        parse_link("115200", 1.0).unwrap(),
        LinkModel::USB_SERIAL_115200
    );
    // 10 bits per byte (8N1): 96 bytes at 115200 baud
    assert_eq!(
        LinkModel::USB_SERIAL_115200.wire_s(96),
        96.0 * 10.0 / 115_200.0
    );
    assert_eq!(LinkModel::FULL_SPEED.wire_s(96), 0.0);
    assert_eq!(
        parse_link("fast", 1.0).unwrap_err(),
        "emulate: --baud fast: allowed are 300–12000000 (bit/s; PI controllers: 115200) or `max` (the pseudo-terminal's full speed)"
    );
    assert!(parse_link("115200", -1.0)
        .unwrap_err()
        .starts_with("emulate: --latency-ms -1: allowed are 0–1000"));
}
