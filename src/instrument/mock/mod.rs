//! A tiny **mock** instrument for tests, examples and benchmarks of the scan engine — not a
//! physical model and not the product's default instrument (that is the simulator).
//!
//! The QPD returns an analytic signal of a point-like object at the origin:
//! g = exp(−(x² + y²)/0.16 µm²) · exp(−z²/0.5 µm²), **sx = x·g**, **sy = 0.7·y·g**,
//! **sz = 1 − 0.1·g** (x, y, z in µm), without noise. The stage records every command it is
//! sent, so tests can assert what was (not) commanded, and both devices can be told to fail
//! or to raise the abort flag after a given number of operations.

use crate::instrument::{
    Clock, DeviceError, Instrument, Pos, Qpd, QpdReading, Stage, VirtualClock,
};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

/// The mock's analytic signal at stage position `p` (µm): (sx, sy, sz).
pub fn mock_signal(p: Pos) -> (f64, f64, f64) {
    let [x, y, z] = p;
    let g = (-(x * x + y * y) / 0.16).exp() * (-(z * z) / 0.5).exp();
    (x * g, 0.7 * y * g, 1.0 - 0.1 * g)
}

/// How to build a mock instrument (all optional, with defaults).
#[derive(Debug, Clone)]
pub struct MockConfig {
    /// Settle time after each move, s (virtual).
    pub settle_s: f64,
    /// QPD sample rate, Hz.
    pub rate_hz: f64,
    /// Stage travel range per axis, µm.
    pub travel: [(f64, f64); 3],
    /// Initial position, µm.
    pub start: Pos,
    /// The stage fails (disconnects) on the move after this many successful moves.
    pub fail_move_after: Option<usize>,
    /// The QPD times out on the read after this many successful reads.
    pub fail_read_after: Option<usize>,
    /// Raise the abort flag (as one Ctrl-C would) once, at this read.
    pub abort_after_reads: Option<(usize, Arc<AtomicBool>)>,
}

impl Default for MockConfig {
    fn default() -> Self {
        Self {
            settle_s: 1e-3,
            rate_hz: 100_000.0,
            travel: [(-50.0, 50.0), (-50.0, 50.0), (-10.0, 10.0)],
            start: [0.0; 3],
            fail_move_after: None,
            fail_read_after: None,
            abort_after_reads: None,
        }
    }
}

/// Shared view into a mock instrument: the command log and the true position.
#[derive(Debug, Clone, Default)]
pub struct MockHandle {
    pub log: Arc<Mutex<Vec<String>>>,
    pub pos: Arc<Mutex<Pos>>,
}

impl MockHandle {
    /// Every command sent so far (`"move 1 2 0"`, `"position?"`, `"read 100"`, ...).
    pub fn commands(&self) -> Vec<String> {
        self.log.lock().map(|l| l.clone()).unwrap_or_default()
    }
    /// Only the move commands.
    pub fn moves(&self) -> Vec<String> {
        self.commands()
            .into_iter()
            .filter(|c| c.starts_with("move"))
            .collect()
    }
    /// The true stage position.
    pub fn position(&self) -> Pos {
        self.pos.lock().map(|p| *p).unwrap_or([f64::NAN; 3])
    }
    fn push(&self, s: String) {
        if let Ok(mut l) = self.log.lock() {
            l.push(s);
        }
    }
}

pub struct MockStage {
    h: MockHandle,
    travel: [(f64, f64); 3],
    moves_ok: usize,
    fail_after: Option<usize>,
    broken: bool,
}

impl Stage for MockStage {
    fn name(&self) -> String {
        "mock stage".into()
    }
    fn position(&mut self) -> Result<Pos, DeviceError> {
        self.h.push("position?".into());
        if self.broken {
            return Err(self.disconnected("POS?"));
        }
        Ok(self.h.position())
    }
    fn move_to(&mut self, t: Pos) -> Result<(), DeviceError> {
        self.h.push(format!("move {} {} {}", t[0], t[1], t[2]));
        let cmd = format!("MOV X {} Y {} Z {}", t[0], t[1], t[2]);
        if self.broken || self.fail_after.is_some_and(|k| self.moves_ok >= k) {
            self.broken = true;
            return Err(self.disconnected(&cmd));
        }
        for (v, (lo, hi)) in t.iter().zip(self.travel) {
            if !(*v >= lo && *v <= hi) {
                return Err(DeviceError::Controller {
                    device: "mock stage".into(),
                    command: cmd,
                    code: 7,
                    message: "position out of limits".into(),
                });
            }
        }
        *self.h.pos.lock().map_err(|_| self.disconnected("MOV"))? = t;
        self.moves_ok += 1;
        Ok(())
    }
    fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError> {
        self.h.push("range?".into());
        Ok(self.travel)
    }
    fn stop(&mut self) -> Result<(), DeviceError> {
        self.h.push("stop".into());
        Ok(())
    }
}

impl MockStage {
    fn disconnected(&self, cmd: &str) -> DeviceError {
        DeviceError::Disconnected {
            device: "mock stage".into(),
            command: cmd.into(),
            detail: "no reply, cable unplugged".into(),
        }
    }
}

pub struct MockQpd {
    h: MockHandle,
    clock: Arc<dyn Clock>,
    rate: f64,
    reads: usize,
    fail_after: Option<usize>,
    abort_after: Option<(usize, Arc<AtomicBool>)>,
}

impl Qpd for MockQpd {
    fn name(&self) -> String {
        "mock QPD".into()
    }
    fn sample_rate(&self) -> f64 {
        self.rate
    }
    fn read(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        self.h.push(format!("read {n}"));
        if self.fail_after.is_some_and(|k| self.reads >= k) {
            return Err(DeviceError::Timeout {
                device: "mock QPD".into(),
                command: "MEAS:QPD?".into(),
                timeout_ms: 500,
            });
        }
        self.clock.wait(n as f64 / self.rate);
        self.reads += 1;
        if let Some((k, flag)) = &self.abort_after {
            if self.reads == *k {
                flag.store(true, Ordering::SeqCst);
            }
        }
        let (sx, sy, sz) = mock_signal(self.h.position());
        Ok(QpdReading {
            sx,
            sy,
            sz,
            sx_std: 0.0,
            sy_std: 0.0,
            sz_std: 0.0,
            n,
            clipped: [0; 3],
        })
    }
}

/// Build a mock instrument on a fresh virtual clock, and the handle to inspect it.
pub fn mock_instrument(cfg: MockConfig) -> (Instrument, MockHandle) {
    let h = MockHandle {
        log: Arc::default(),
        pos: Arc::new(Mutex::new(cfg.start)),
    };
    let clock: Arc<dyn Clock> = Arc::new(VirtualClock::new());
    let stage = MockStage {
        h: h.clone(),
        travel: cfg.travel,
        moves_ok: 0,
        fail_after: cfg.fail_move_after,
        broken: false,
    };
    let qpd = MockQpd {
        h: h.clone(),
        clock: clock.clone(),
        rate: cfg.rate_hz,
        reads: 0,
        fail_after: cfg.fail_read_after,
        abort_after: cfg.abort_after_reads.clone(),
    };
    let inst = Instrument {
        stage: Box::new(stage),
        qpd: Box::new(qpd),
        clock,
        settle_s: cfg.settle_s,
        description: serde_json::json!({
            "backend": "mock",
            "stage": "mock stage",
            "qpd": "mock QPD (analytic signal sx = x·exp(-(x²+y²)/0.16)·exp(-z²/0.5))",
            "settle_s": cfg.settle_s,
            "sample_rate_hz": cfg.rate_hz,
            "travel_um": cfg.travel,
        }),
    };
    (inst, h)
}

/// The mock instrument of the tests and examples. (listed in `instrument::registry`).
pub const FAMILY: crate::instrument::family::Family = crate::instrument::family::Family {
    keys: &[
        "rate",
        "start",
        "fail_move_after",
        "fail_read_after",
        "abort_after_reads",
    ],
    help: crate::instrument::family::ConnectHelp {
        backend: "\"mock\"",
        about: "The mock backend is for tests and examples: a noiseless analytic signal \
             sx = x·exp(-(x²+y²)/0.16)·exp(-z²/0.5), sy = 0.7·y·(same), sz = 1 - 0.1·(same), on a \
             virtual clock, travel x, y ±50 µm, z ±10 µm. It can be told to fail or to raise the \
             abort flag, to test the safety rules from scripts.",
    },
    ..crate::instrument::family::Family::new("mock", "mock", crate::instrument::family::Open::Mock)
};
