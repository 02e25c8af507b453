//! `libfakebench.so`: a fake of the paper's bench for testing bfpscope's drivers: a Mad City
//! Labs Nano-Drive (Nano-PDQ375 stage) behind the **Madlib** C API and an NI PCI-6120 board
//! behind the **NI-DAQmx** C API, in one shared library so that the two devices are coupled as
//! on the bench: the stage position moves the bead under the focus (the QPD inputs of the
//! board), the board's AO channels drive the Nano-Drive's external inputs, and one AI channel
//! records the Nano-Drive's sensor monitor.
//!
//! Written from the vendors' public headers and documents only (Madlib.h as published with
//! Micro-Manager's MCL_NanoDrive adapter and MCL's Python/Matlab examples; NIDAQmx.h; NI's
//! published error texts), never from bfpscope's drivers: a misreading in a driver is caught
//! here. See `README.md` beside this crate and `docs/hardware.md` ("The fake Nano-Drive and
//! PCI-6120 for tests").
//!
//! Exported symbols: the Madlib functions (`MCL_*`, [`madlib`]), the NI-DAQmx functions
//! (`DAQmx*`, [`daqmx`]) and a control/inspection API for tests (`fakebench_*`, [`control`]).
//! Every exported function catches panics and answers with the vendor's error code instead.
//!
//! Time is wall time: a move settles with the configured lag, an acquisition of n samples at
//! rate r takes n / r seconds, a continuous task fills its buffer as time passes.

pub mod config;
pub mod control;
pub mod daqmx;
pub mod errors;
pub mod madlib;
pub mod scene;
pub mod stage;

use std::io::Write;
use std::sync::{Mutex, MutexGuard, OnceLock};
use std::time::Instant;

pub use config::Config;

/// Seconds since the library's first use (the bench's clock).
pub fn now() -> f64 {
    static EPOCH: OnceLock<Instant> = OnceLock::new();
    EPOCH.get_or_init(Instant::now).elapsed().as_secs_f64()
}

/// Sleep until the bench clock reads `t` (s).
pub fn sleep_until(t: f64) {
    let dt = t - now();
    if dt > 0.0 && dt.is_finite() {
        std::thread::sleep(std::time::Duration::from_secs_f64(dt));
    }
}

/// The whole bench: configuration, the Nano-Drive, the PCI-6120, the call log.
pub struct Bench {
    pub cfg: Config,
    pub stage: stage::NanoDrive,
    pub mcl: madlib::State,
    pub daq: daqmx::Board,
    pub qpd: scene::Qpd,
    pub log: Vec<String>,
    log_file: Option<std::fs::File>,
}

/// Most lines kept in the in-memory call log (the file log, `FAKEBENCH_LOG`, keeps all).
const LOG_CAP: usize = 200_000;

impl Bench {
    /// A bench from `cfg` (at the bench clock's present time).
    pub fn new(cfg: Config) -> Self {
        let t = now();
        let log_file = cfg.log_path.as_ref().and_then(|p| {
            std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(p)
                .ok()
        });
        Bench {
            stage: stage::NanoDrive::new(&cfg, t),
            mcl: madlib::State::default(),
            daq: daqmx::Board::new(&cfg),
            qpd: scene::Qpd::new(&cfg),
            cfg,
            log: Vec::new(),
            log_file,
        }
    }

    /// Append one line to the call log (`name(arg=value, …) -> result`).
    pub fn log(&mut self, line: String) {
        if let Some(f) = self.log_file.as_mut() {
            let _ = writeln!(f, "{line}");
        }
        if self.log.len() >= LOG_CAP {
            self.log.drain(..LOG_CAP / 2);
        }
        self.log.push(line);
    }
}

static BENCH: Mutex<Option<Bench>> = Mutex::new(None);

/// The bench, built from the environment (`FAKEBENCH_*`) on first use.
pub fn bench() -> MutexGuard<'static, Option<Bench>> {
    let mut g = BENCH.lock().unwrap_or_else(|e| e.into_inner());
    if g.is_none() {
        let cfg = Config::from_env();
        *g = Some(Bench::new(cfg));
    }
    g
}

/// Run `f` on the bench (locked).
pub fn with_bench<R>(f: impl FnOnce(&mut Bench) -> R) -> R {
    let mut g = bench();
    f(g.as_mut().expect("bench initialised by bench()"))
}

/// Replace the bench by a new one from `cfg` (tests: a fresh bench with other settings).
pub fn replace_bench(cfg: Config) {
    let mut g = BENCH.lock().unwrap_or_else(|e| e.into_inner());
    *g = Some(Bench::new(cfg));
}

/// Read a C string (NULL → empty).
///
/// # Safety
/// `p` is NULL or a NUL-terminated string.
pub(crate) unsafe fn cstr(p: *const std::os::raw::c_char) -> String {
    if p.is_null() {
        String::new()
    } else {
        std::ffi::CStr::from_ptr(p).to_string_lossy().into_owned()
    }
}

/// Copy `s` into a C buffer of `size` bytes (truncated, NUL-terminated). Returns the size the
/// whole string needs with its NUL.
///
/// # Safety
/// `buf` is NULL or points to `size` writable bytes.
pub(crate) unsafe fn put_cstr(s: &str, buf: *mut std::os::raw::c_char, size: usize) -> usize {
    let bytes = s.as_bytes();
    if !buf.is_null() && size > 0 {
        let n = bytes.len().min(size - 1);
        std::ptr::copy_nonoverlapping(bytes.as_ptr(), buf as *mut u8, n);
        *buf.add(n) = 0;
    }
    bytes.len() + 1
}

/// Run `f`, turning a panic into `fallback` (no panic crosses the C boundary).
pub(crate) fn guard<R>(fallback: R, f: impl FnOnce() -> R) -> R {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).unwrap_or(fallback)
}
