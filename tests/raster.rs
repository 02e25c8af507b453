//! Hardware-timed raster lines (the PI part): the GCS stage emulator's wave
//! generator, trigger outputs and data recorder, spoken to over loopback TCP in raw GCS, then
//! the driver's line sweep.

use bfpscope::instrument::emulator::{
    shared_position, start_stage_emulator_tcp, Emulator, ExtTrigger, StageEmulatorConfig,
    WaveConfig,
};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

const DT: f64 = 50e-6;
const TAU: f64 = 0.5e-3;

fn emu_with(wave: WaveConfig) -> Emulator {
    let cfg = StageEmulatorConfig {
        start: [10.0, 10.0, 5.0],
        settle_s: 0.002,
        wave,
        ..StageEmulatorConfig::default()
    };
    start_stage_emulator_tcp(cfg, shared_position([0.0; 3]), "127.0.0.1:0").unwrap()
}

fn emu() -> Emulator {
    emu_with(WaveConfig {
        servo_cycle_s: DT,
        lag_s: TAU,
        ..WaveConfig::default()
    })
}

/// A raw GCS client: one line out, the (multi-line) reply back.
struct Raw {
    s: TcpStream,
    buf: Vec<u8>,
}

impl Raw {
    fn connect(emu: &Emulator) -> Raw {
        let addr = emu.path().trim_start_matches("tcp://").to_string();
        let s = TcpStream::connect(addr).unwrap();
        s.set_read_timeout(Some(Duration::from_millis(50))).unwrap();
        Raw { s, buf: Vec::new() }
    }

    fn send(&mut self, cmd: &str) {
        self.s.write_all(format!("{cmd}\n").as_bytes()).unwrap();
    }

    /// The reply's lines up to one without the trailing space (marker spaces kept).
    fn reply(&mut self) -> String {
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            if let Some(end) = (0..self.buf.len())
                .find(|&i| self.buf[i] == b'\n' && (i == 0 || self.buf[i - 1] != b' '))
            {
                let r: Vec<u8> = self.buf.drain(..=end).collect();
                return String::from_utf8_lossy(&r[..r.len() - 1]).to_string();
            }
            assert!(Instant::now() < deadline, "no reply; have {:?}", self.buf);
            let mut chunk = [0u8; 65536];
            // a read timeout just loops back to the deadline check
            if let Ok(n) = self.s.read(&mut chunk) {
                self.buf.extend_from_slice(&chunk[..n]);
            }
        }
    }

    fn query(&mut self, q: &str) -> String {
        self.send(q);
        self.reply()
    }

    fn err(&mut self) -> i64 {
        self.query("ERR?").trim().parse().unwrap()
    }

    /// Send `cmd` and expect no error.
    fn ok(&mut self, cmd: &str) {
        self.send(cmd);
        assert_eq!(self.err(), 0, "{cmd}");
    }

    /// Send `cmd` and expect error `code`.
    fn fails(&mut self, cmd: &str, code: i64) {
        self.send(cmd);
        assert_eq!(self.err(), code, "{cmd}");
    }

    /// `#9`: running generators as a bit mask.
    fn running(&mut self) -> u32 {
        self.s.write_all(&[0x09]).unwrap();
        u32::from_str_radix(self.reply().trim(), 16).unwrap()
    }

    /// Poll `#9` until no generator runs (bounded: 10 s).
    fn wait_generators(&mut self) {
        let deadline = Instant::now() + Duration::from_secs(10);
        while self.running() != 0 {
            assert!(Instant::now() < deadline, "the generator never stopped");
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    fn pos(&mut self, axis: &str) -> f64 {
        let r = self.query(&format!("POS? {axis}"));
        r.split('=').nth(1).unwrap().trim().parse().unwrap()
    }

    /// Move axis 1 to `x` and wait until it is on target.
    fn park(&mut self, x: f64) {
        self.ok(&format!("MOV 1 {x}"));
        let deadline = Instant::now() + Duration::from_secs(5);
        while self.query("ONT? 1").trim() != "1=1" {
            assert!(Instant::now() < deadline);
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}

/// Parse a GCS array as PIPython does (`getgcsheader`, `_convertfloats`): header lines
/// `# KEY = VALUE`, then rows of numbers.
fn gcs_array(reply: &str) -> (std::collections::BTreeMap<String, String>, Vec<Vec<f64>>) {
    let mut header = std::collections::BTreeMap::new();
    let mut rows = Vec::new();
    let mut in_header = true;
    for line in reply.split('\n') {
        if in_header {
            assert!(line.starts_with('#'), "header line {line:?}");
            assert!(
                line.ends_with(' '),
                "header line without its marker space: {line:?}"
            );
            let l = line.trim_start_matches('#').trim();
            if l == "END_HEADER" {
                in_header = false;
                continue;
            }
            if let Some((k, v)) = l.split_once('=') {
                header.insert(k.trim().to_string(), v.trim().to_string());
            }
        } else {
            rows.push(
                line.split_whitespace()
                    .map(|v| v.parse::<f64>().unwrap())
                    .collect(),
            );
        }
    }
    (header, rows)
}

/// A single LIN line of `n` points from 10 to 30 µm (no speed-up) in table 1 on generator 1,
/// one cycle, recording target and current position of axis 1 every servo cycle.
fn setup_line(c: &mut Raw, n: usize) {
    c.ok("SVO 1 1 2 1 3 1");
    c.park(10.0);
    c.ok(&format!("WAV 1 X LIN {n} 20 10 {n} 0 0"));
    c.ok("WSL 1 1");
    c.ok("WGC 1 1");
    c.ok("WTR 1 1 0");
    c.ok("DRC 1 1 1 2 1 2");
    c.ok("RTR 1");
}

#[test]
fn lin_sweep_records_the_ramp_and_the_position_lagging_it() {
    let e = emu();
    let mut c = Raw::connect(&e);
    let n = 2000;
    setup_line(&mut c, n);
    assert_eq!(c.query("WAV? 1 1"), "1 1=2000");
    assert_eq!(c.query("WSL? 1"), "1=1");
    assert_eq!(c.query("WGC? 1"), "1=1");
    assert_eq!(c.query("WTR? 1"), "1=1 0");
    assert_eq!(c.query("DRC? 1 2"), "1=1 1 \n2=1 2");
    assert_eq!(c.query("RTR?"), "1");
    c.ok("WGO 1 1");
    assert_eq!(c.query("WGO? 1"), "1=1");
    c.wait_generators();
    let drl = c.query("DRL? 1");
    let recorded: usize = drl.split('=').nth(1).unwrap().parse().unwrap();
    assert!(recorded >= n, "{drl}");
    let (h, rows) = gcs_array(&c.query(&format!("DRR? 1 {n} 1 2")));
    assert_eq!(c.err(), 0);
    assert_eq!(h["VERSION"], "1");
    assert_eq!(h["SEPARATOR"], "32");
    assert_eq!(h["DIM"], "2");
    assert_eq!(h["NDATA"], n.to_string());
    assert_eq!(h["SAMPLE_TIME"].parse::<f64>().unwrap(), DT);
    assert_eq!(h["NAME0"], "Target Position of axis 1");
    assert_eq!(h["NAME1"], "Current Position of axis 1");
    assert_eq!(rows.len(), n);
    // the target is the ramp, point j at servo cycle j
    let step = 20.0 / (n - 1) as f64;
    for (j, r) in rows.iter().enumerate() {
        assert_eq!(r.len(), 2);
        assert!(
            (r[0] - (10.0 + step * j as f64)).abs() <= 1e-6,
            "{j}: {r:?}"
        );
    }
    // steady state: the first-order lag trails by v·dt/(exp(dt/τ) − 1) (v·dt = one step)
    let lag = step / ((DT / TAU).exp() - 1.0);
    assert!((lag - step * (TAU / DT - 0.5)).abs() < 1e-4, "{lag}"); // ≈ v·(τ − dt/2)
    for (j, r) in rows.iter().enumerate().skip(300) {
        assert!((r[0] - r[1] - lag).abs() <= 2e-6, "{j}: {r:?}, lag {lag}");
    }
    // it started without a jump: the first samples trail by less than the steady lag
    assert!((rows[0][1] - 10.0).abs() < step);
    // the axis settles at the last point and is on target
    std::thread::sleep(Duration::from_millis(20));
    assert!((c.pos("1") - 30.0).abs() < 1e-6);
    assert_eq!(c.query("ONT? 1"), "1=1");
    // the default DRR? reads every table with a record option, all points
    c.send("DRR?");
    let (h, _) = gcs_array(&c.reply());
    assert_eq!(h["DIM"], "2");
}

#[test]
fn wgo_0_stops_the_generator_and_the_axis_holds() {
    let e = emu();
    let mut c = Raw::connect(&e);
    setup_line(&mut c, 20_000); // a 1 s line
    c.ok("WGC 1 0"); // endless
    c.ok("WGO 1 1");
    std::thread::sleep(Duration::from_millis(30));
    assert_eq!(c.running(), 1);
    // motion commands are refused while the generator drives the axis
    c.fails("MOV 1 12", 73);
    c.fails("SVO 1 0", 73);
    c.fails("WSL 1 2", 73);
    c.fails("WAV 1 X LIN 10 1 0 10 0 0", 73);
    c.ok("WGO 1 0");
    assert_eq!(c.running(), 0);
    assert_eq!(c.query("WGO? 1"), "1=0");
    std::thread::sleep(Duration::from_millis(20)); // 40 τ
    let p1 = c.pos("1");
    std::thread::sleep(Duration::from_millis(20));
    let p2 = c.pos("1");
    assert!(p1 > 10.0 && p1 < 30.0, "{p1}");
    assert_eq!(p1, p2, "the axis holds where the generator stopped");
    assert_eq!(c.query("ONT? 1"), "1=1");
    // and moves again
    c.park(11.0);
    assert!((c.pos("1") - 11.0).abs() < 1e-9);
}

#[test]
fn stp_stops_the_generator_with_error_10() {
    let e = emu();
    let mut c = Raw::connect(&e);
    setup_line(&mut c, 20_000);
    c.ok("WGO 1 1");
    std::thread::sleep(Duration::from_millis(10));
    c.send("STP");
    assert_eq!(c.err(), 10);
    assert_eq!(c.running(), 0);
    let p1 = c.pos("1");
    std::thread::sleep(Duration::from_millis(20));
    assert_eq!(p1, c.pos("1"), "stopped where it was");
}

#[test]
fn wrong_arguments_get_the_manuals_error_codes() {
    let e = emu_with(WaveConfig {
        table_points: 100,
        ..WaveConfig::default()
    });
    let mut c = Raw::connect(&e);
    c.fails("WGO 1 1", 75); // no wave table selected
    c.ok("WAV 1 X LIN 50 200 0 50 0 0"); // 0 … 200 µm: beyond the 100 µm travel
    c.ok("WSL 1 1");
    c.fails("WGO 1 1", 5); // servo off
    c.ok("SVO 1 1");
    c.fails("WGO 1 1", 7); // the wave leaves the travel range
    c.fails("WGO 1 2", 17); // external-trigger start is not emulated
    c.fails("WSL 4 1", 17); // no generator 4
    c.fails("WSL 1 9", 17); // no table 9
    c.fails("WAV 9 X LIN 10 1 0 10 0 0", 17);
    c.fails("WAV 1 X LIN 10 1 0", 1); // too few arguments
    c.fails("WAV 1 X LIN 10 1 0 20 0 0", 17); // curve longer than its segment
    c.fails("WAV 1 X LIN 10 1 0 10 0 5", 17); // speed-up and -down longer than the curve
    c.fails("WAV 1 X LIN 200 1 0 200 0 0", 67); // more than the table holds
    c.fails("WAV 1 Q LIN 10 1 0 10 0 0", 1);
    c.fails("WAV 1 X SIN 10 1 0 10 0 0", 1);
    c.fails("WAV 1 X PNT 1 3 1 2", 1); // 3 points announced, 2 given
    c.ok("WAV 2 X PNT 1 3 1 2 3");
    c.ok("WAV 2 & PNT 1 2 4 5");
    assert_eq!(c.query("WAV? 2 1"), "2 1=5");
    c.fails("WTR 1 0 0", 17);
    c.fails("CTO 1 3 1", 17); // trigger mode 1 does not exist
    c.fails("CTO 4 3 0", 17); // no OUT4
    c.fails("CTO 1 2 7", 15); // no axis 7
    c.fails("CTO 1 3", 1);
    c.fails("DRC 99 1 2", 57);
    c.fails("DRC 1 1 9", 58);
    c.fails("DRC 1 7 2", 59);
    c.fails("RTR 0", 17);
    c.ok("DRC 1 1 2");
    c.send("DRR? 1 10 1"); // nothing recorded yet: no reply, error 77
    assert_eq!(c.err(), 77);
    c.send("DRR? 1 10 9");
    assert_eq!(c.err(), 57);
    // WGO? and friends name the generator
    assert_eq!(c.query("WSL?"), "1=1 \n2=0 \n3=0");
}

#[test]
fn generator_trigger_pulses_the_wired_input_once_per_cycle() {
    let t = ExtTrigger::new();
    let e = emu_with(WaveConfig {
        trigger_out: [Some(t.clone()), None, None],
        ..WaveConfig::default()
    });
    let mut c = Raw::connect(&e);
    setup_line(&mut c, 200);
    c.ok("WGC 1 3");
    c.ok("CTO 1 2 1 1 3 4");
    c.ok("TWS 1 1 1 1 2 0"); // high at point 1, low from point 2
    assert_eq!(c.query("CTO? 1 3 1 2"), "1 3=4 \n1 2=1");
    assert_eq!(t.count(), 0);
    c.ok("WGO 1 1");
    c.wait_generators();
    assert_eq!(
        t.count(),
        3,
        "one pulse at the start of each of the 3 cycles"
    );
}

#[test]
fn position_distance_trigger_fires_between_start_and_stop_thresholds() {
    let t = ExtTrigger::new();
    let e = emu_with(WaveConfig {
        trigger_out: [Some(t.clone()), None, None],
        ..WaveConfig::default()
    });
    let mut c = Raw::connect(&e);
    setup_line(&mut c, 2000);
    // pulses at 15, 17, …, 25 µm, moving up only
    c.ok("CTO 1 2 1 1 3 0 1 1 2 1 8 15 1 9 25");
    c.ok("WGO 1 1");
    c.wait_generators();
    assert_eq!(t.count(), 6);
    // back down through the window: no pulse (wrong direction)
    c.park(10.0);
    std::thread::sleep(Duration::from_millis(10));
    assert_eq!(t.count(), 6);
}

// ---------------------------------------------------------------------------------------
// The driver's line sweep, over a pseudo-terminal.

use bfpscope::instrument::emulator::start_stage_emulator;
use bfpscope::instrument::gcs::{parse_gcs_array, GcsOptions, GcsStage, LineSweep};
use bfpscope::instrument::{DeviceError, Stage};
use std::sync::atomic::AtomicBool;

fn pty_stage(wave: WaveConfig) -> (Emulator, GcsStage) {
    let cfg = StageEmulatorConfig {
        start: [10.0, 10.0, 5.0],
        settle_s: 0.002,
        wave,
        ..StageEmulatorConfig::default()
    };
    let e = start_stage_emulator(cfg, shared_position([0.0; 3])).unwrap();
    let opts = GcsOptions {
        timeout: Duration::from_millis(1000),
        on_target_timeout: Duration::from_millis(1000),
        poll_interval: Duration::from_millis(1),
        ..GcsOptions::default()
    };
    let mut s = GcsStage::open(e.path(), 115_200, opts).unwrap();
    Stage::enable(&mut s).unwrap();
    (e, s)
}

fn line(from: f64, to: f64) -> LineSweep {
    LineSweep {
        axis: 0,
        from_um: from,
        to_um: to,
        points: 400,
        speedupdown: 20,
        rate: 1,
        record_rate: 1,
        trigger_line: Some(1),
        table: 1,
        servo_cycle_s: DT,
    }
}

#[test]
fn driver_sweeps_a_line_pulses_the_trigger_once_and_reads_the_recorder() {
    let t = ExtTrigger::new();
    let (e, mut s) = pty_stage(WaveConfig {
        servo_cycle_s: DT,
        lag_s: TAU,
        trigger_out: [Some(t.clone()), None, None],
        ..WaveConfig::default()
    });
    let l = line(10.0, 20.0);
    Stage::move_to(&mut s, [10.0, 10.0, 5.0]).unwrap();
    let rec = s
        .sweep_line(&l, &AtomicBool::new(false))
        .unwrap()
        .expect("not aborted");
    assert_eq!(t.count(), 1, "one trigger pulse per line");
    assert_eq!(rec.sample_time_s, DT);
    assert_eq!(rec.target_um.len(), 400);
    assert_eq!(rec.position_um.len(), 400);
    assert!((rec.target_um[0] - 10.0).abs() <= 1e-6);
    assert!((rec.target_um[399] - 20.0).abs() <= 1e-6);
    // constant speed between the speed-up and the speed-down: v = 10 µm / (379 · 50 µs)
    let v = l.speed_um_s();
    assert!((v - 10.0 / (379.0 * DT)).abs() < 1e-9 * v);
    for j in 30..370 {
        let d = rec.target_um[j + 1] - rec.target_um[j];
        assert!((d - v * DT).abs() <= 2e-6, "{j}: {d}");
    }
    // the measured position trails by v·dt/(exp(dt/τ) − 1) once the lag has settled (≥ 10 τ
    // into the constant-speed part)
    let lag = v * DT / ((DT / TAU).exp() - 1.0);
    for j in 250..370 {
        let e = rec.target_um[j] - rec.position_um[j];
        assert!((e - lag).abs() <= 3e-6, "{j}: {e} vs {lag}");
    }
    let log = e.commands();
    assert!(log
        .iter()
        .any(|c| c == "WAV 1 X LIN 400 10.000000 10.000000 400 0 20"));
    assert!(log.iter().any(|c| c == "WGO 1 1"));
    assert!(log.iter().any(|c| c == "DRR? 1 400 1 2"));
    assert!(!log.iter().any(|c| c == "STP"), "no stop on a good line");
    // the driver reads the target again after the generator moved the axis
    assert!((Stage::target(&mut s).unwrap()[0] - 20.0).abs() < 1e-6);
}

#[test]
fn aborted_line_stops_the_generator_and_the_axes() {
    let (e, mut s) = pty_stage(WaveConfig::default());
    let mut l = line(10.0, 20.0);
    l.points = 20_000; // 1 s
    let r = s.sweep_line(&l, &AtomicBool::new(true)).unwrap();
    assert!(r.is_none());
    let log = e.commands();
    let i = log.iter().position(|c| c == "WGO 1 1").unwrap();
    let tail: Vec<&str> = log[i..].iter().map(String::as_str).collect();
    assert!(
        tail.contains(&"WGO 1 0") && tail.contains(&"STP"),
        "{tail:?}"
    );
    let mut c = s.query_only("WGO? 1").unwrap();
    assert_eq!(c.remove(0), "1=0");
}

#[test]
fn a_recorder_that_never_fills_is_a_fault_that_stops_everything() {
    // record tables of 100 points: the 400 asked never come
    let (e, mut s) = pty_stage(WaveConfig {
        record_points: 100,
        ..WaveConfig::default()
    });
    let err = s
        .sweep_line(&line(10.0, 20.0), &AtomicBool::new(false))
        .unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("DRL? 1 2") && msg.contains("[100, 100]") && msg.contains("400"),
        "{msg}"
    );
    assert!(matches!(err, DeviceError::Other { .. }));
    let log = e.commands();
    let n = log.len();
    assert!(
        log[n - 3..].iter().any(|c| c == "WGO 1 0"),
        "{:?}",
        &log[n - 4..]
    );
    assert!(
        log[n - 3..].iter().any(|c| c == "STP"),
        "{:?}",
        &log[n - 4..]
    );
}

#[test]
fn a_rejected_line_names_the_command_and_the_controller_error() {
    // a wave beyond the 100 µm travel: WGO is refused with error 7
    let (e, mut s) = pty_stage(WaveConfig::default());
    let err = s
        .sweep_line(&line(10.0, 120.0), &AtomicBool::new(false))
        .unwrap_err();
    match &err {
        DeviceError::Controller { command, code, .. } => {
            assert_eq!(command, "WGO 1 1");
            assert_eq!(*code, 7);
        }
        other => panic!("{other}"),
    }
    assert!(err.to_string().contains("Position out of limits"));
    assert!(e.commands().iter().any(|c| c == "STP"));
}

#[test]
fn gcs_array_parser_reads_pipython_s_format_and_names_what_is_wrong() {
    let ok: Vec<String> = [
        "# VERSION = 1",
        "# TYPE = 1",
        "# SEPARATOR = 32",
        "# DIM = 2",
        "# SAMPLE_TIME = 0.000050",
        "# NDATA = 2",
        "# NAME0 = Target Position of axis 1",
        "# END_HEADER",
        "1.5 2.5",
        "3.5 4.5",
    ]
    .map(String::from)
    .to_vec();
    let a = parse_gcs_array(&ok).unwrap();
    assert_eq!(a.columns, vec![vec![1.5, 3.5], vec![2.5, 4.5]]);
    assert_eq!(a.get("NAME0"), Some("Target Position of axis 1"));
    let mut short = ok.clone();
    short.pop();
    assert_eq!(parse_gcs_array(&short).unwrap_err(), "1 rows, NDATA is 2");
    let mut bad = ok.clone();
    bad[9] = "3.5 x".into();
    assert!(parse_gcs_array(&bad)
        .unwrap_err()
        .contains("row 2 is not numbers"));
    let mut one = ok;
    one[9] = "3.5".into();
    assert!(parse_gcs_array(&one)
        .unwrap_err()
        .contains("row 2 has 1 values, DIM is 2"));
}
