//! The Red Pitaya STEMlab driver against the board's emulator over loopback TCP (no hardware).
//!
//! The emulator is written from Red Pitaya's public command reference, the driver from the
//! same document; these tests check that they agree on the protocol and that what the driver
//! reports is what the emulated inputs carried: known signals at known stage positions, known
//! ramps on a known time base, and every fault named with device, command and reply.

use crate::support::cleanup;

use bfpscope::config::connect::{connect, ConnectError};
use bfpscope::config::Config;
use bfpscope::instrument::emulator::{
    shared_position, standin_bead, start_redpitaya_emulator, start_stage_emulator, Emulator,
    ExtTrigger, Faults, RedPitayaEmulatorConfig, StageEmulatorConfig,
};
use bfpscope::instrument::redpitaya::{ChannelMap, RedPitaya, RedPitayaOptions};
use bfpscope::instrument::scpi::Calibration;
use bfpscope::instrument::{DeviceError, Instrument, Qpd, Trigger};
use std::io::{Read, Write};
use std::sync::Arc;
use std::time::Duration;

/// Detector gain of the emulated QPD (volts per signal unit, Sx Sy Sz) and input offsets.
const VPU: [f64; 3] = [2.0, 2.0, 4.0];
const OFFSET: [f64; 4] = [0.1, -0.1, 0.05, 0.0];

fn calibration() -> Calibration {
    Calibration {
        gain: [1.0 / VPU[0], 1.0 / VPU[1], 1.0 / VPU[2]],
        offset_v: [OFFSET[0], OFFSET[1], OFFSET[2]],
    }
}

fn emu_cfg(four: bool, noise_v: f64) -> RedPitayaEmulatorConfig {
    let base = if four {
        RedPitayaEmulatorConfig::four_inputs()
    } else {
        RedPitayaEmulatorConfig::default()
    };
    RedPitayaEmulatorConfig {
        volts_per_unit: VPU,
        offset_v: OFFSET,
        noise_v,
        ..base
    }
}

fn start(cfg: RedPitayaEmulatorConfig, at: [f64; 3]) -> (Emulator, ExtTrigger) {
    start_redpitaya_emulator(cfg, shared_position(at), standin_bead, "127.0.0.1:0").unwrap()
}

fn host_port(e: &Emulator) -> (String, u16) {
    let hp = e.path().trim_start_matches("tcp://");
    let (h, p) = hp.rsplit_once(':').unwrap();
    (h.to_string(), p.parse().unwrap())
}

fn opts(four: bool, timeout_ms: u64) -> RedPitayaOptions {
    RedPitayaOptions {
        timeout: Duration::from_millis(timeout_ms),
        calibration: calibration(),
        channels: ChannelMap {
            sx: 1,
            sy: 2,
            sz: four.then_some(3),
        },
        ..RedPitayaOptions::default()
    }
}

/// The driver sent `ACQ:STOP` after the emulator's command `from` (waits for the emulator to
/// log it: a silent board still reads its commands).
fn assert_stopped(e: &Emulator, from: usize) {
    for _ in 0..500 {
        if e.commands()[from..].iter().any(|x| x == "ACQ:STOP") {
            return;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    panic!("no ACQ:STOP: {:?}", &e.commands()[from..]);
}

fn open(e: &Emulator, four: bool, timeout_ms: u64) -> RedPitaya {
    let (h, p) = host_port(e);
    RedPitaya::open(&h, p, opts(four, timeout_ms)).unwrap()
}

#[test]
fn connect_identifies_the_board_and_sets_binary_volts() {
    let (e, _) = start(emu_cfg(false, 0.0), [0.0; 3]);
    let rp = open(&e, false, 1000);
    assert!(rp.idn().starts_with("REDPITAYA,"), "{}", rp.idn());
    assert_eq!(rp.buffer_size(), 16384);
    let (h, p) = host_port(&e);
    assert_eq!(rp.name(), format!("Red Pitaya on {h}:{p}"));
    let cmds = e.commands();
    for c in [
        "*IDN?",
        "ACQ:RST",
        "ACQ:DATA:FORMAT BIN",
        "ACQ:DATA:UNITS VOLTS",
        "ACQ:BUF:SIZE?",
        "ACQ:SOUR1:GAIN LV",
        "ACQ:SOUR2:GAIN LV",
    ] {
        assert!(cmds.iter().any(|x| x == c), "{c} not sent: {cmds:?}");
    }
    // no input 3 asked of a 2-input board
    assert!(!cmds.iter().any(|x| x.starts_with("ACQ:SOUR3")), "{cmds:?}");
}

/// An input beyond the board's ±1 V (LV jumpers): the emulated ADC saturates at the rail and
/// the driver counts every sample of that input as clipped; the other input counts none.
#[test]
fn samples_at_the_lv_rail_are_counted_as_clipped() {
    // Sx 0.8 units × 2 V + 0.1 V = 1.7 V against ±1 V; Sy 0.1 × 2 − 0.1 = 0.1 V
    let (e, _) = start_redpitaya_emulator(
        emu_cfg(false, 0.0),
        shared_position([0.0; 3]),
        |_: [f64; 3]| [0.8, 0.1, 0.0],
        "127.0.0.1:0",
    )
    .unwrap();
    let mut rp = open(&e, false, 1000);
    let r = rp.read(100).unwrap();
    assert_eq!(r.clipped, [r.n, 0, 0], "{r}");
    // the rail's reading: (1 V − 0.1 V) / 2 V per unit
    assert!((r.sx - 0.45).abs() < 1e-3, "{r}");
    assert_eq!(rp.input_range().expect("known").full_scale, 1.0);
}

/// The standin bead's (Sx, Sy, Sz) at `p` (µm).
fn exact(p: [f64; 3]) -> [f64; 3] {
    standin_bead(p)
}

#[test]
fn point_read_recovers_the_scene_at_the_stage_position_within_the_noise() {
    let at = [0.1, -0.05, 0.2];
    let noise = 2e-3; // volts rms per ADC sample
    let (e, _) = start(emu_cfg(true, noise), at);
    let mut rp = open(&e, true, 2000);
    // 100 samples at the nominal 100 kHz: a 1 ms window, recorded at decimation 8 (the
    // smallest whose 16384 samples span ≥ 1 ms), 15625 samples
    let r = rp.read(100).unwrap();
    assert_eq!(r.n, 15625);
    let cmds = e.commands();
    assert!(cmds.iter().any(|c| c == "ACQ:DEC 8"), "{cmds:?}");
    assert!(cmds.iter().any(|c| c == "ACQ:TRIG:DLY 7433"), "{cmds:?}"); // 15625 − 8192
    assert!(cmds.iter().any(|c| c == "ACQ:TRIG NOW"), "{cmds:?}");
    assert!(
        cmds.iter()
            .any(|c| c.starts_with("ACQ:SOUR3:DATA:STA:N? ") && c.ends_with(",15625")),
        "{cmds:?}"
    );
    let want = exact(at);
    // per-sample noise after 8× averaging, in signal units
    for (i, (got, got_std)) in [(r.sx, r.sx_std), (r.sy, r.sy_std), (r.sz, r.sz_std)]
        .into_iter()
        .enumerate()
    {
        let sigma = noise / 8f64.sqrt() / VPU[i];
        let se = sigma / (15625f64).sqrt();
        assert!(
            (got - want[i]).abs() < 5.0 * se,
            "channel {i}: {got} vs {} (standard error {se})",
            want[i]
        );
        // the sample standard deviation of 15625 samples: relative spread 1/√(2·15624) = 0.57 %
        assert!(
            (got_std / sigma - 1.0).abs() < 0.03,
            "channel {i}: std {got_std} vs {sigma}"
        );
    }
    // a second read at the same dwell does not resend the settings
    let before = e.commands().len();
    rp.read(100).unwrap();
    let again = &e.commands()[before..];
    assert!(!again.iter().any(|c| c.starts_with("ACQ:DEC")), "{again:?}");
}

#[test]
fn two_input_board_reads_sx_and_sy_and_reports_sz_zero() {
    let at = [0.2, 0.1, 0.0];
    let (e, _) = start(emu_cfg(false, 0.0), at);
    let mut rp = open(&e, false, 2000);
    let r = rp.read(10).unwrap();
    let want = exact(at);
    // no noise: float32 volts, 1e-7 relative
    assert!((r.sx - want[0]).abs() < 1e-6, "{r}");
    assert!((r.sy - want[1]).abs() < 1e-6, "{r}");
    assert_eq!((r.sz, r.sz_std), (0.0, 0.0));
    // 10 samples at 100 kHz = 100 µs: decimation 1, 12500 samples
    assert_eq!(r.n, 12500);
}

#[test]
fn longer_dwell_decimates_further_and_too_long_is_refused() {
    let (e, _) = start(emu_cfg(false, 0.0), [0.0; 3]);
    let mut rp = open(&e, false, 2000);
    // 0.2 s: 0.2 · 125e6 / 16384 = 1525.9 → decimation 2048, round(0.2 · 125e6 / 2048) = 12207
    let r = rp.read(20_000).unwrap();
    assert_eq!(r.n, 12207);
    assert!(e.commands().iter().any(|c| c == "ACQ:DEC 2048"));
    // 10 s is longer than the 8.59 s the buffer holds at decimation 65536: refused, nothing sent
    let before = e.commands().len();
    let err = rp.read(1_000_000).unwrap_err().to_string();
    assert!(
        err.contains("read(1000000) at 100000 Hz: read window 10 s: longer than the 8.590 s"),
        "{err}"
    );
    assert_eq!(e.commands().len(), before);
}

/// A point's dwell is the board's acquisition window itself (`Qpd::read_for`): 33 µs at the
/// nominal 100 kHz would be 3 samples = 30 µs through a sample count; the board records
/// round(33e-6 · 125e6) = 4125 samples at decimation 1 (33.0 µs), the window asked for.
#[test]
fn a_dwell_is_read_as_its_own_window_with_no_round_trip_through_samples() {
    use bfpscope::instrument::Qpd;
    let (e, _) = start(emu_cfg(false, 0.0), [0.0; 3]);
    let mut rp = open(&e, false, 2000);
    let r = rp.read_for(33e-6).unwrap();
    assert_eq!(r.n, 4125);
    let r = rp
        .read(bfpscope::instrument::samples_per_point(33e-6, 100e3))
        .unwrap();
    assert_eq!(r.n, 3750);
    // 0.2 s as a window is the same acquisition as read(20 000) at 100 kHz (see below)
    let r = rp.read_for(0.2).unwrap();
    assert_eq!(r.n, 12207);
    assert!(e.commands().iter().any(|c| c == "ACQ:DEC 2048"));
}

#[test]
fn buffered_read_recovers_a_ramp_on_its_time_base() {
    // a function generator on the inputs: IN1 ramps 400 V/s, IN2 −200 V/s from the trigger
    let gen: bfpscope::instrument::emulator::Generator =
        Arc::new(|t: f64| [400.0 * t, -200.0 * t, 0.0, 0.0]);
    let at = [0.1, 0.0, 0.0];
    let cfg = RedPitayaEmulatorConfig {
        generator: Some(gen),
        ..emu_cfg(false, 0.0)
    };
    let (e, ext) = start(cfg, at);
    let mut rp = open(&e, false, 1000);
    // 1000 samples at 1 MHz (a 1 ms line): 125 MHz / 64 = 1.953 MHz is the slowest rate ≥ 1 MHz,
    // ceil(1 ms · 1.953 MHz) = 1954 samples
    let arm = rp.arm_buffered(1000, 1e6, Trigger::ExternalRising).unwrap();
    assert_eq!(arm.n_samples, 1954);
    assert_eq!(arm.sample_rate, 125e6 / 64.0);
    assert!(e.commands().iter().any(|c| c == "ACQ:TRIG EXT_PE"));
    // the controller's trigger output fires
    ext.pulse();
    let t = rp.read_buffered(Duration::from_secs(2)).unwrap();
    assert_eq!(t.len(), 1954);
    assert_eq!(t.dt_s, 64.0 / 125e6);
    // the driver reads from the sample after TPOS (the last before the trigger) and dates it at
    // the expected middle of its averaging window: 0
    assert_eq!(t.t0_s, 0.0);
    assert!(!t.sz_measured);
    let base = exact(at);
    // the decimator's phase at the trigger (windows counted from ACQ:START) is unknown to the
    // driver: the true times are t_i + δ with one δ for the trace, |δ| ≤ dt/2 (Red Pitaya's
    // FPGA scope); find it on the first sample, then every sample must agree with it
    let delta = (t.sx[0] * VPU[0] - VPU[0] * base[0]) / 400.0 - t.time(0);
    assert!(
        delta.abs() <= 0.5 * t.dt_s + 1e-9,
        "δ = {delta} s, dt = {} s",
        t.dt_s
    );
    for i in 0..t.len() {
        let ti = t.time(i) + delta;
        let sx = (400.0 * ti + VPU[0] * base[0]) / VPU[0];
        let sy = (-200.0 * ti + VPU[1] * base[1]) / VPU[1];
        assert!(
            (t.sx[i] - sx).abs() < 1e-6,
            "sample {i} at {ti} s: {} vs {sx}",
            t.sx[i]
        );
        assert!(
            (t.sy[i] - sy).abs() < 1e-6,
            "sample {i}: {} vs {sy}",
            t.sy[i]
        );
        assert_eq!(t.sz[i], 0.0);
    }
}

#[test]
fn external_trigger_that_never_comes_times_out_naming_the_state_query_and_stops() {
    let (e, ext) = start(emu_cfg(false, 0.0), [0.0; 3]);
    let mut rp = open(&e, false, 1000);
    // a pulse before arming does not count
    ext.pulse();
    rp.arm_buffered(100, 1e5, Trigger::ExternalRising).unwrap();
    let from = e.commands().len();
    let err = rp.read_buffered(Duration::from_millis(200)).unwrap_err();
    match &err {
        DeviceError::Other { device, detail } => {
            assert!(device.starts_with("Red Pitaya on 127.0.0.1:"), "{device}");
            assert!(
                detail.contains("no trigger within 200 ms: `ACQ:TRIG:STAT?` still answers \"WAIT\" (source EXT_PE"),
                "{detail}"
            );
            assert!(detail.contains("DIO0_P"), "{detail}");
        }
        other => panic!("{other:?}"),
    }
    assert_stopped(&e, from);
}

#[test]
fn trigger_fault_on_a_point_read_names_the_query_and_stops() {
    let (e, _) = start(emu_cfg(false, 0.0), [0.0; 3]);
    let mut rp = open(&e, false, 300);
    e.faults().no_trigger = true;
    let from = e.commands().len();
    let err = rp.read(100).unwrap_err().to_string();
    assert!(
        err.contains("`ACQ:TRIG:STAT?` still answers \"WAIT\" (source NOW"),
        "{err}"
    );
    assert_stopped(&e, from);
    // the fault cleared, the next read works
    e.faults().no_trigger = false;
    if let Err(e) = rp.read(100) {
        panic!("{e}");
    }
}

#[test]
fn silent_board_is_a_timeout_naming_the_command() {
    let (e, _) = start(emu_cfg(false, 0.0), [0.0; 3]);
    let mut rp = open(&e, false, 200);
    e.faults().silent = true;
    let from = e.commands().len();
    match rp.read(100) {
        Err(DeviceError::Timeout {
            device,
            command,
            timeout_ms,
        }) => {
            assert!(device.starts_with("Red Pitaya on 127.0.0.1:"), "{device}");
            assert_eq!(command, "SYST:ERR? (after `ACQ:DEC 8`)");
            assert_eq!(timeout_ms, 200);
        }
        other => panic!("{other:?}"),
    }
    assert_stopped(&e, from);
    // silent from the start: the connect's first query
    let (e2, _) = start(
        RedPitayaEmulatorConfig {
            faults: Faults {
                silent: true,
                ..Faults::default()
            },
            ..emu_cfg(false, 0.0)
        },
        [0.0; 3],
    );
    let (h, p) = host_port(&e2);
    match RedPitaya::open(&h, p, opts(false, 200)) {
        Err(DeviceError::Timeout { command, .. }) => assert_eq!(command, "*IDN?"),
        Err(other) => panic!("{other:?}"),
        Ok(_) => panic!("connected to a silent board"),
    }
}

#[test]
fn garbled_replies_are_garbled_errors_with_the_text() {
    let (e, _) = start(emu_cfg(false, 0.0), [0.0; 3]);
    let mut rp = open(&e, false, 300);
    e.faults().garble_replies = 1;
    match rp.read(100) {
        Err(DeviceError::Garbled { command, reply, .. }) => {
            assert_eq!(command, "SYST:ERR? (after `ACQ:DEC 8`)");
            assert!(reply.contains("#,\"No error\""), "{reply:?}");
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn input_the_board_does_not_have_is_the_boards_error() {
    // Sz on IN3 of a 2-input board
    let (e, _) = start(emu_cfg(false, 0.0), [0.0; 3]);
    let (h, p) = host_port(&e);
    match RedPitaya::open(&h, p, opts(true, 500)) {
        Err(DeviceError::Controller {
            command,
            code,
            message,
            ..
        }) => {
            assert_eq!(command, "ACQ:SOUR3:GAIN LV");
            assert_eq!(code, -113);
            assert_eq!(message, "Undefined header");
        }
        Err(other) => panic!("{other:?}"),
        Ok(_) => panic!("IN3 accepted on a 2-input board"),
    }
}

/// Send `cmd` (CR LF) on a raw socket and read `n` bytes of reply.
fn raw(s: &mut std::net::TcpStream, cmd: &str) {
    s.write_all(format!("{cmd}\r\n").as_bytes()).unwrap();
}

fn read_until_crlf(s: &mut std::net::TcpStream) -> Vec<u8> {
    let mut out = Vec::new();
    let mut b = [0u8; 1];
    while !out.ends_with(b"\r\n") {
        s.read_exact(&mut b).unwrap();
        out.push(b[0]);
    }
    out
}

#[test]
fn emulator_data_formats_as_the_document_describes() {
    let at = [0.1, 0.0, 0.0];
    let (e, _) = start(emu_cfg(false, 0.0), at);
    let (h, p) = host_port(&e);
    let mut s = std::net::TcpStream::connect((h.as_str(), p)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    raw(&mut s, "ACQ:DEC 1");
    raw(&mut s, "ACQ:TRIG:DLY -8189"); // 3 samples after the trigger
    raw(&mut s, "ACQ:START");
    raw(&mut s, "ACQ:TRIG NOW");
    raw(&mut s, "ACQ:TRIG:STAT?");
    assert_eq!(read_until_crlf(&mut s), b"TD\r\n");
    raw(&mut s, "ACQ:TRIG:FILL?");
    assert_eq!(read_until_crlf(&mut s), b"1\r\n");
    raw(&mut s, "ACQ:TPOS?");
    let tpos = String::from_utf8(read_until_crlf(&mut s)).unwrap();
    let tpos: usize = tpos.trim().parse().unwrap();
    // ASCII volts: {v1,v2,v3}, "%f"
    let v = VPU[0] * exact(at)[0] + OFFSET[0];
    raw(&mut s, &format!("ACQ:SOUR1:DATA:STA:N? {tpos},3"));
    let want = format!("{{{v:.6},{v:.6},{v:.6}}}\r\n");
    assert_eq!(String::from_utf8(read_until_crlf(&mut s)).unwrap(), want);
    // ASCII raw counts: 14 bits, 8192 at the LV full scale of 1 V
    raw(&mut s, "ACQ:DATA:UNITS RAW");
    raw(&mut s, &format!("ACQ:SOUR1:DATA:STA:N? {tpos},2"));
    let c = (v * 8192.0).round() as i64;
    assert_eq!(
        String::from_utf8(read_until_crlf(&mut s)).unwrap(),
        format!("{{{c},{c}}}\r\n")
    );
    // BIN volts: #<digits><length> then big-endian float32, then CR LF
    raw(&mut s, "ACQ:DATA:UNITS VOLTS");
    raw(&mut s, "ACQ:DATA:FORMAT BIN");
    raw(&mut s, &format!("ACQ:SOUR1:DATA:STA:N? {tpos},3"));
    let mut hdr = [0u8; 4];
    s.read_exact(&mut hdr).unwrap();
    assert_eq!(&hdr, b"#212");
    let mut body = [0u8; 14];
    s.read_exact(&mut body).unwrap();
    assert_eq!(&body[12..], b"\r\n");
    assert_eq!(
        f32::from_be_bytes([body[0], body[1], body[2], body[3]]),
        v as f32
    );
    // a wrong command: no reply, the error in the queue
    raw(&mut s, "ACQ:SOUR1:DATA:STA:N? 16384,3");
    raw(&mut s, "SYST:ERR?");
    assert_eq!(
        String::from_utf8(read_until_crlf(&mut s)).unwrap(),
        "-222,\"Data out of range\"\r\n"
    );
}

// ---------------------------------------------------------------------------------------------
// Config and connect

fn config_error(text: &str) -> bfpscope::config::ConfigError {
    Config::from_toml_str(text, "test.toml").expect_err("must be refused")
}

const STAGE: &str = "[stage]\nbackend = \"gcs\"\nport = \"/dev/ttyUSB0\"\n";

#[test]
fn config_errors_name_the_key_and_value() {
    let e = config_error(&format!("{STAGE}[qpd]\nbackend = \"redpitaya\"\n"));
    assert_eq!(e.key, "qpd.host");
    assert!(
        e.message.contains("required when backend = \"redpitaya\""),
        "{e}"
    );
    let e = config_error(&format!(
        "{STAGE}[qpd]\nbackend = \"redpitaya\"\nhost = \"rp.local\"\nchannels = {{ sx = 1, sy = 1 }}\n"
    ));
    assert_eq!(e.key, "qpd.channels.sy");
    assert!(e.message.contains("input 1 is already sx"), "{e}");
    let e = config_error(&format!(
        "{STAGE}[qpd]\nbackend = \"redpitaya\"\nhost = \"rp.local\"\nchannels = {{ sx = 1, sy = 2, sz = 5 }}\n"
    ));
    assert_eq!(e.key, "qpd.channels.sz");
    assert!(e.message.contains("input 5"), "{e}");
    let e = config_error(&format!(
        "{STAGE}[qpd]\nbackend = \"redpitaya\"\nhost = \"192.168.1.100:5000\"\n"
    ));
    assert_eq!(e.key, "qpd.host");
    assert!(e.message.contains("\"192.168.1.100:5000\""), "{e}");
    let e = config_error(&format!(
        "{STAGE}[qpd]\nbackend = \"redpitaya\"\nhost = \"rp.local\"\nport = \"fivethousand\"\n"
    ));
    assert_eq!(e.key, "qpd.port");
    assert!(e.message.contains("\"fivethousand\""), "{e}");
    let e = config_error(&format!(
        "{STAGE}[qpd]\nbackend = \"redpitaya\"\nhost = \"rp.local\"\nsample_rate_hz = 0.0\n"
    ));
    assert_eq!(e.key, "qpd.sample_rate_hz");
    // a good one: port as a number, the 4-input channel map
    let c = Config::from_toml_str(
        &format!(
            "{STAGE}[qpd]\nbackend = \"redpitaya\"\nhost = \"rp.local\"\nport = 5001\n\
             channels = {{ sx = 2, sy = 1, sz = 4 }}\ninput_gain = \"HV\"\n"
        ),
        "test.toml",
    )
    .unwrap();
    assert_eq!(
        bfpscope::instrument::redpitaya::config::port(&c.qpd).unwrap(),
        5001
    );
    let o = bfpscope::instrument::redpitaya::config::options(&c.qpd);
    assert_eq!(
        o.channels,
        ChannelMap {
            sx: 2,
            sy: 1,
            sz: Some(4)
        }
    );
    assert_eq!(o.gain.as_str(), "HV");
}

fn no_sim(_: &Config) -> anyhow::Result<Instrument> {
    panic!("the simulator must not be built for a hardware config")
}

#[test]
fn unreachable_board_names_the_device_and_address() {
    let stage = start_stage_emulator(
        StageEmulatorConfig {
            travel: [(-2.0, 2.0), (-2.0, 2.0), (-1.0, 1.0)],
            ..Default::default()
        },
        shared_position([0.0; 3]),
    )
    .unwrap();
    // a port nobody listens on
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let text = format!(
        "[stage]\nbackend = \"gcs\"\nport = \"{}\"\n[qpd]\nbackend = \"redpitaya\"\nhost = \"127.0.0.1\"\nport = {port}\ntimeout_ms = 300\n",
        stage.path()
    );
    let cfg = Config::from_toml_str(&text, "test.toml").unwrap();
    match connect(&cfg, no_sim) {
        Err(ConnectError::Device(DeviceError::Other { device, detail })) => {
            assert_eq!(device, format!("Red Pitaya on 127.0.0.1:{port}"));
            assert!(
                detail.contains(&format!("cannot connect to tcp://127.0.0.1:{port}")),
                "{detail}"
            );
            assert!(detail.contains("SCPI server"), "{detail}");
        }
        Err(other) => panic!("{other}"),
        Ok(_) => panic!("connected to nothing"),
    }
}

#[test]
fn scan_through_bfpscope_with_an_emulated_stage_and_the_red_pitaya_saves_a_scan_file() {
    use bfpscope::script::{Settings, Workbench};
    let pos = shared_position([0.0; 3]);
    let stage = start_stage_emulator(
        StageEmulatorConfig {
            travel: [(-2.0, 2.0), (-2.0, 2.0), (-1.0, 1.0)],
            settle_s: 0.001,
            ..Default::default()
        },
        pos.clone(),
    )
    .unwrap();
    let (rp, _ext) =
        start_redpitaya_emulator(emu_cfg(true, 0.0), pos, standin_bead, "127.0.0.1:0").unwrap();
    let (h, p) = host_port(&rp);
    let text = format!(
        r#"
[stage]
backend = "gcs"
port = "{}"
poll_ms = 1
settle_s = 0.0

[qpd]
backend = "redpitaya"
host = "{h}"
port = {p}
channels = {{ sx = 1, sy = 2, sz = 3 }}
calibration = {{ gain = [{}, {}, {}], offset_v = [{}, {}, {}] }}
"#,
        stage.path(),
        1.0 / VPU[0],
        1.0 / VPU[1],
        1.0 / VPU[2],
        OFFSET[0],
        OFFSET[1],
        OFFSET[2]
    );
    let cfg = Config::from_toml_str(&text, "test.toml").unwrap();
    let dir = std::env::temp_dir().join(format!("bfpscope-rp-scan-{}", std::process::id()));
    cleanup::at_exit(&dir);
    let _ = std::fs::remove_dir_all(&dir);
    let (mut settings, _buf) = Settings::captured(&dir);
    settings.apply_config(cfg, None).unwrap();
    let mut wb = Workbench::new(settings);
    let r = wb.eval_source("t", "connect()").unwrap().to_string();
    assert!(r.contains("Red Pitaya on 127.0.0.1:"), "{r}");
    let _scan = wb
        .eval_source(
            "t",
            "scan_line(#{axis: \"x\", from: -0.4, to: 0.4, n: 5, dwell: 0.001})",
        )
        .unwrap();
    // the scan file is on disk, and holds what the inputs carried
    let files: Vec<_> = walk(&dir)
        .into_iter()
        .filter(|p| p.extension().is_some_and(|e| e == "npz"))
        .collect();
    assert_eq!(files.len(), 1, "{files:?}");
    let scan = bfpscope::data::npz::load_scan(&files[0]).unwrap();
    assert_eq!(scan.meta["instrument"]["qpd"]["backend"], "redpitaya");
    for (i, x) in [-0.4, -0.2, 0.0, 0.2, 0.4].iter().enumerate() {
        let want = exact([*x, 0.0, 0.0]);
        // no noise: float32 volts
        for (c, img) in [&scan.sx, &scan.sy, &scan.sz].into_iter().enumerate() {
            let got = img.data[[0, i]];
            assert!(
                (got - want[c]).abs() < 1e-6,
                "x = {x}, channel {c}: {got} vs {}",
                want[c]
            );
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

fn walk(d: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut out = vec![];
    if let Ok(rd) = std::fs::read_dir(d) {
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                out.extend(walk(&p));
            } else {
                out.push(p);
            }
        }
    }
    out
}

#[test]
fn connect_at_the_prompt_names_the_board_and_reconnects_to_the_same_address() {
    use bfpscope::script::{Settings, Workbench};
    let pos = shared_position([0.0; 3]);
    let stage = start_stage_emulator(
        StageEmulatorConfig {
            travel: [(-2.0, 2.0), (-2.0, 2.0), (-1.0, 1.0)],
            ..Default::default()
        },
        pos.clone(),
    )
    .unwrap();
    let (rp, _ext) =
        start_redpitaya_emulator(emu_cfg(false, 0.0), pos, standin_bead, "127.0.0.1:0").unwrap();
    let (h, p) = host_port(&rp);
    let dir = std::env::temp_dir().join(format!("bfpscope-rp-wb-{}", std::process::id()));
    cleanup::at_exit(&dir);
    let (settings, _buf) = Settings::captured(&dir);
    let mut wb = Workbench::new(settings);
    let call = format!(
        "connect(#{{backend: \"redpitaya\", stage_port: \"{}\", qpd_host: \"{h}\", qpd_port: \"{p}\"}})",
        stage.path()
    );
    let r = wb.eval_source("t", &call).unwrap().to_string();
    assert_eq!(
        r,
        format!(
            "connected hardware: PI E-727 on {}, Red Pitaya on {h}:{p}",
            stage.path()
        )
    );
    // again: the board serves one client at a time, so the old connection is closed first
    let r = wb.eval_source("t", &call).unwrap().to_string();
    assert!(r.ends_with(&format!("Red Pitaya on {h}:{p}")), "{r}");
    let st = wb
        .eval_source("t", "[status().instrument.qpd.backend, ct(0.001).n]")
        .unwrap();
    assert_eq!(
        bfpscope::script::show(&st),
        "[\"redpitaya\", 15625]".to_string()
    );
    // qpd_host on a SCPI QPD is refused, naming the key
    let e = wb
        .eval_source(
            "t",
            "connect(#{backend: \"hardware\", stage_port: \"/dev/x\", qpd_host: \"rp.local\"})",
        )
        .unwrap_err();
    assert!(
        e.message.contains(
            "connect: qpd_host applies to a Red Pitaya QPD (backend \"redpitaya\"), not \"scpi\""
        ),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn board_error_and_unplugged_board_name_device_and_command() {
    let (e, _) = start(emu_cfg(false, 0.0), [0.0; 3]);
    let mut rp = open(&e, false, 300);
    // the board rejects the next command with its error code
    e.faults().error_next = Some(-200);
    match rp.read(100) {
        Err(DeviceError::Controller { command, code, .. }) => {
            assert_eq!((command.as_str(), code), ("ACQ:DEC 8", -200));
        }
        other => panic!("{other:?}"),
    }
    // the next read works again
    assert_eq!(rp.read(100).unwrap().n, 15625);
    // the cable is pulled after two more commands
    e.faults().unplug_after = Some(2);
    match rp.read(100) {
        Err(DeviceError::Disconnected {
            device, command, ..
        }) => {
            assert!(device.starts_with("Red Pitaya on 127.0.0.1:"), "{device}");
            // ACQ:START and its error query are served, then the line goes dead
            assert_eq!(command, "SYST:ERR? (after `ACQ:TRIG NOW`)");
        }
        other => panic!("{other:?}"),
    }
}
