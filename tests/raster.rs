//! Hardware-timed raster lines (issue 21, the PI part): the GCS stage emulator's wave
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
