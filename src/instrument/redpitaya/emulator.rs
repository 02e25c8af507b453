//! A Red Pitaya STEMlab emulator: the board's SCPI server on a loopback TCP port, written from
//! Red Pitaya's public command reference (`commands-acq`, `redpitaya_scpi.py`; see
//! `docs/hardware.md`, "Red Pitaya STEMlab"), not from the driver.
//!
//! What it models:
//! - 2 inputs (STEMlab 125-14) or 4 (its 4-input model), a 16384-sample ring buffer per input,
//!   written at 125 MS/s / decimation (`ACQ:DEC`, powers of two 1…65536); with `ACQ:AVG ON`
//!   (the default) a decimated sample averages `dec` ADC samples, so the white noise per sample
//!   is `noise_v / √dec`;
//! - `ACQ:START`/`ACQ:STOP` (clears the trigger source)/`ACQ:RST`; trigger sources `DISABLED`, `NOW`, `CHn_PE/NE` (level
//!   `ACQ:TRIG:LEV`), `EXT_PE/NE` (pulses on [`ExtTrigger`], the extension connector's DIO0_P),
//!   `AWG_PE/NE` (accepted, never fires: no generator is emulated); when the trigger fires the
//!   source reads back `DISABLED`, and `ACQ:TRIG:STAT?` answers `TD` exactly when the source is
//!   `DISABLED` (so before any `ACQ:TRIG`, too), `WAIT` otherwise;
//! - `ACQ:TRIG:DLY d`: `8192 + d` samples are written after the trigger (clamped to 0…16383),
//!   then writing stops and `ACQ:TRIG:FILL?` answers 1; all in wall-clock time;
//! - the time of a sample as the FPGA scope (`red_pitaya_scope.v`) makes it: the decimator's
//!   windows of `dec` ADC samples start at `ACQ:START`, a sample is written at the end of its
//!   window (the mean of the window with `ACQ:AVG ON`, its last ADC sample with `OFF`), and
//!   `ACQ:TPOS?` is the last sample written before the trigger; a sample carries the signal at
//!   the middle of its window (see `Board::fire`);
//! - `ACQ:WPOS?`, `ACQ:TPOS?`, `ACQ:BUF:SIZE?`, `ACQ:SOUR<n>:GAIN LV|HV` (inputs clip at ±1 V /
//!   ±20 V; RAW counts are 14-bit, ±8192 at full scale);
//! - data: `ACQ:SOUR<n>:DATA?` (the whole buffer from the oldest sample), `:DATA:STA:N? s,n`,
//!   `:DATA:STA:END? s,e`, `:DATA:OLD:N? n`, `:DATA:LAT:N? n`, in `ACQ:DATA:UNITS VOLTS|RAW`
//!   and `ACQ:DATA:FORMAT ASCII|BIN`: ASCII `{v1,v2,…}` (volts as `%f`, raw as integers); BIN
//!   `#<k><len><bytes>` of `f32` volts or `i16` counts, big-endian unless
//!   `ACQ:DATA:BYTE:ORDER LEND`; every reply ends in CR LF;
//! - errors: a wrong or malformed command gets no reply and leaves `code,"message"` in the
//!   error queue read by `SYST:ERR?` (`SYST:ERR:NEXT?`); `*STB?` bit 2 says the queue is not
//!   empty; `*CLS` clears it.
//!
//! The signal: each input carries the volts of the [`SignalSource`] at the stage position
//! (`volts = volts_per_unit · signal + offset`, Sx → IN1, Sy → IN2, Sz → IN3 by default), plus
//! an optional test generator (volts per input as a function of the sample's time since the
//! trigger) and white noise. The position: with a [`StagePath`] shared with the GCS stage
//! emulator (`RedPitayaEmulatorConfig::path`) and a wave running, sample j (j = 0 at TPOS)
//! carries the signal at the path's position at the middle of its averaging window,
//! `trigger + (j − ½)·dt − phase` (the trigger dated by the external pulse's edge,
//! [`ExtTrigger::last_edge`]; `phase` < dt from the decimator's count since `ACQ:START`): the
//! board follows the moving stage during a hardware-timed line. Otherwise (and for earlier
//! samples) the shared position at the trigger.
//!
//! Faults ([`Faults`]): `silent` (reads commands, never answers), `garble_replies` (text replies
//! garbled, binary blocks lose their `#`), `no_trigger` (no trigger source ever fires, `NOW`
//! included), `error_next`, `reject` (the n+1-th command with a given first word, e.g. the 6th
//! `ACQ:START`, fails with a code), `unplug_after` (closes the connection and stops).
//!
//! Not modelled: deep-memory (DMA) acquisition, split triggers, `ACQ:TRIG:DLY:NS`, hysteresis,
//! the generator outputs (`SOUR<n>:…`), calibration offsets, the pre-trigger fill condition, a
//! stage stopped during an acquisition after the trigger (the samples are computed at the
//! trigger from the path as published then).

use crate::instrument::emulation::{
    garble, launch, lock, Emulator, ExtTrigger, Faults, SharedPosition, SignalSource, StagePath,
    LOG_CAP,
};
use rand::{Rng, SeedableRng};
use std::collections::VecDeque;
use std::io::{Read, Write};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

const BUF: usize = 16384;
const BASE_RATE_HZ: f64 = 125e6;
const QUEUE: usize = 16;
/// Spacing of the nodes a moving stage's signal is evaluated on, µm (see `Board::volts_along`).
const PATH_NODE_UM: f64 = 0.005;

/// Volts per input (IN1..IN4) as a function of seconds since the trigger: a function generator
/// wired to the inputs in a bench test.
pub type Generator = Arc<dyn Fn(f64) -> [f64; 4] + Send + Sync>;

/// The signal source at many stage positions in one call (the simulator renders a row of
/// positions in one pass: [`sim_signal_along`](crate::instrument::emulator::sim_signal_along)), for the nodes of a
/// path.
pub type PathSource = Arc<dyn Fn(&[crate::instrument::Pos]) -> Vec<[f64; 3]> + Send + Sync>;

/// Red Pitaya emulator settings.
#[derive(Clone)]
pub struct RedPitayaEmulatorConfig {
    /// `*IDN?` reply (the server answers `REDPITAYA,INSTR<year>,<build date>,<commit>`).
    pub idn: String,
    /// Fast analog inputs: 2 (STEMlab 125-14) or 4 (its 4-input model).
    pub inputs: usize,
    /// Input (1-based) each signal Sx, Sy, Sz is wired to; 0: not wired.
    pub wiring: [usize; 3],
    /// Detector gain: volts per signal unit for Sx, Sy, Sz.
    pub volts_per_unit: [f64; 3],
    /// DC offset per input, volts.
    pub offset_v: [f64; 4],
    /// White noise per ADC sample (decimation 1), volts rms; averaging divides it by √dec.
    pub noise_v: f64,
    /// Noise seed.
    pub seed: u64,
    /// Extra volts per input vs time since the trigger (tests: a known ramp).
    pub generator: Option<Generator>,
    /// The path of the stage under a running wave generator (shared with the GCS stage
    /// emulator, [`WaveConfig::path`](crate::instrument::gcs::emulator::WaveConfig::path)): each sample after the trigger
    /// carries the signal at the stage position at its own time. `None`: the position is
    /// taken once, at the trigger.
    pub path: Option<StagePath>,
    /// The source at a path's nodes in one call; `None`: one call of the source per node.
    /// Only the board's cost changes (a simulated scene rendered node by node took ~0.4 s a
    /// line in a debug build, inside the trigger's handling, where a real board takes none).
    pub along: Option<PathSource>,
    /// Initial fault switches.
    pub faults: Faults,
}

impl Default for RedPitayaEmulatorConfig {
    fn default() -> Self {
        Self {
            idn: "REDPITAYA,INSTR2020,0,bfpscope-emulator".into(),
            inputs: 2,
            wiring: [1, 2, 0],
            volts_per_unit: [1.0; 3],
            offset_v: [0.0; 4],
            noise_v: 1e-3,
            seed: 1,
            generator: None,
            path: None,
            along: None,
            faults: Faults::default(),
        }
    }
}

impl RedPitayaEmulatorConfig {
    /// The 4-input model with Sz wired to IN3.
    pub fn four_inputs() -> Self {
        Self {
            inputs: 4,
            wiring: [1, 2, 3],
            ..Self::default()
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Src {
    Disabled,
    Now,
    ChPe(usize),
    ChNe(usize),
    ExtPe,
    ExtNe,
    AwgPe,
    AwgNe,
}

const SOURCES: [(&str, Src); 16] = [
    ("DISABLED", Src::Disabled),
    ("NOW", Src::Now),
    ("CH1_PE", Src::ChPe(0)),
    ("CH1_NE", Src::ChNe(0)),
    ("CH2_PE", Src::ChPe(1)),
    ("CH2_NE", Src::ChNe(1)),
    ("CH3_PE", Src::ChPe(2)),
    ("CH3_NE", Src::ChNe(2)),
    ("CH4_PE", Src::ChPe(3)),
    ("CH4_NE", Src::ChNe(3)),
    ("EXT_PE", Src::ExtPe),
    ("EXT_NE", Src::ExtNe),
    ("AWG_PE", Src::AwgPe),
    ("AWG_NE", Src::AwgNe),
    ("EXT_AE", Src::ExtPe),
    ("AWG_AE", Src::AwgPe),
];

/// Where the acquisition is.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Acq {
    /// Not writing (after reset or stop, or before the first start).
    Idle,
    /// Writing since `since`, waiting for the trigger.
    Running { since: Instant, ext_seen: u64 },
    /// Triggered at `at`, `post` samples still to be written after it.
    Triggered { at: Instant, post: usize },
}

struct Board {
    cfg: RedPitayaEmulatorConfig,
    errors: VecDeque<(i64, String)>,
    position: SharedPosition,
    source: Box<dyn SignalSource>,
    ext: ExtTrigger,
    rng: rand_chacha::ChaCha8Rng,
    faults: Arc<Mutex<Faults>>,
    dec: u32,
    avg: bool,
    src: Src,
    level_v: f64,
    delay: i64,
    raw: bool,
    binary: bool,
    little_endian: bool,
    hv: [bool; 4],
    acq: Acq,
    /// Write pointer when writing started (the acquisition begins where the last one ended).
    wpos0: usize,
    /// The last sample written before the trigger (`ACQ:TPOS?`), and where writing stopped.
    tpos: usize,
    /// How long before the trigger the window of the sample at TPOS ended, s (< dt).
    phase_s: f64,
    wstop: usize,
    /// Volts per input and sample.
    data: Vec<Vec<f32>>,
    last_level: [Option<f64>; 4],
    /// `ACQ:TRIG:FILL?`: the post-trigger samples are written.
    filled: bool,
}

/// The text of the SCPI error codes used.
fn error_text(code: i64) -> &'static str {
    match code {
        0 => "No error",
        -102 => "Syntax error",
        -108 => "Parameter not allowed",
        -109 => "Missing parameter",
        -113 => "Undefined header",
        -222 => "Data out of range",
        -224 => "Illegal parameter value",
        -350 => "Queue overflow",
        _ => "Device-specific error",
    }
}

/// A reply: text (CR LF added) or a binary block (CR LF added).
enum Reply {
    Text(String),
    Bin(Vec<u8>),
}

impl Board {
    /// A board just reset (`ACQ:RST`'s state): decimation 1, averaging on, no trigger, text
    /// data, empty buffers of every input.
    fn new(
        cfg: RedPitayaEmulatorConfig,
        position: SharedPosition,
        source: Box<dyn SignalSource>,
        ext: ExtTrigger,
        faults: Arc<Mutex<Faults>>,
    ) -> Board {
        let inputs = cfg.inputs;
        Board {
            rng: rand_chacha::ChaCha8Rng::seed_from_u64(cfg.seed),
            cfg,
            errors: VecDeque::new(),
            position,
            source,
            ext,
            faults,
            dec: 1,
            avg: true,
            src: Src::Disabled,
            level_v: 0.0,
            delay: 0,
            raw: false,
            binary: false,
            little_endian: false,
            hv: [false; 4],
            acq: Acq::Idle,
            wpos0: 0,
            tpos: 0,
            phase_s: 0.0,
            wstop: 0,
            data: vec![vec![0.0; BUF]; inputs],
            last_level: [None; 4],
            filled: false,
        }
    }

    fn push_error(&mut self, code: i64, info: &str) {
        if self.errors.len() >= QUEUE {
            if let Some(last) = self.errors.back_mut() {
                *last = (-350, String::new());
            }
        } else {
            self.errors.push_back((code, info.to_string()));
        }
    }

    fn dt(&self) -> f64 {
        self.dec as f64 / BASE_RATE_HZ
    }

    /// Volts on the inputs from the signal source at the current stage position.
    fn input_volts(&self) -> [f64; 4] {
        let p = *lock(&self.position);
        self.volts_at(p)
    }

    /// Volts on the inputs from the signal source at stage position `p`.
    fn volts_at(&self, p: crate::instrument::Pos) -> [f64; 4] {
        self.volts_of((self.source)(p))
    }

    /// The inputs' volts for signals `s` (Sx, Sy, Sz).
    fn volts_of(&self, s: [f64; 3]) -> [f64; 4] {
        let mut v = self.cfg.offset_v;
        for (i, &w) in self.cfg.wiring.iter().enumerate() {
            if (1..=self.cfg.inputs).contains(&w) {
                v[w - 1] += self.cfg.volts_per_unit[i] * s[i];
            }
        }
        v
    }

    /// Volts at each of `positions` (a path's samples). When only one axis varies, the
    /// source is evaluated on nodes every [`PATH_NODE_UM`] along it (at most 4097 nodes) and
    /// interpolated linearly between them (exact for a source linear in that axis; for a
    /// scene, an error of f''·h²/8, about 1e-4 of the peak for a 300 nm wide response): a
    /// simulated scene costs a rendering per node, not per sample. Otherwise once per
    /// distinct position.
    fn volts_along(&self, positions: &[crate::instrument::Pos]) -> Vec<[f64; 4]> {
        let Some(first) = positions.first().copied() else {
            return Vec::new();
        };
        let varying: Vec<usize> = (0..3)
            .filter(|&a| positions.iter().any(|p| p[a] != first[a]))
            .collect();
        if let [a] = varying[..] {
            let (lo, hi) = positions
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), p| {
                    (l.min(p[a]), h.max(p[a]))
                });
            let n = (((hi - lo) / PATH_NODE_UM).ceil() as usize).clamp(1, 4096);
            let h = (hi - lo) / n as f64;
            let qs: Vec<crate::instrument::Pos> = (0..=n)
                .map(|i| {
                    let mut q = first;
                    q[a] = if i == n { hi } else { lo + i as f64 * h };
                    q
                })
                .collect();
            let nodes: Vec<[f64; 4]> = match &self.cfg.along {
                Some(f) => f(&qs).into_iter().map(|s| self.volts_of(s)).collect(),
                None => qs.iter().map(|&q| self.volts_at(q)).collect(),
            };
            return positions
                .iter()
                .map(|p| {
                    let u = if h > 0.0 { (p[a] - lo) / h } else { 0.0 };
                    let i = (u.floor().max(0.0) as usize).min(n.saturating_sub(1));
                    let f = if n == 0 { 0.0 } else { u - i as f64 };
                    let (v0, v1) = (nodes[i], nodes[(i + 1).min(n)]);
                    std::array::from_fn(|c| v0[c] + f * (v1[c] - v0[c]))
                })
                .collect();
        }
        let mut last: Option<(crate::instrument::Pos, [f64; 4])> = None;
        positions
            .iter()
            .map(|&pos| match last {
                Some((lp, v)) if lp == pos => v,
                _ => {
                    let v = self.volts_at(pos);
                    last = Some((pos, v));
                    v
                }
            })
            .collect()
    }

    /// Samples written after the trigger: `8192 + ACQ:TRIG:DLY`, after the sample at TPOS.
    fn post_samples(&self) -> usize {
        (BUF as i64 / 2 + self.delay).clamp(0, BUF as i64 - 1) as usize
    }

    fn elapsed_samples(&self, since: Instant, now: Instant) -> usize {
        ((now - since).as_secs_f64() / self.dt()) as usize
    }

    /// The trigger fired at `now` (at the external pulse's edge for `EXT_*`).
    ///
    /// As Red Pitaya's FPGA scope does: the decimator restarts its count at `ACQ:START` and
    /// writes a sample each time `dec` ADC samples are summed, at the end of their window;
    /// the trigger saves the write pointer of the last sample written before it (`TPOS`). So
    /// with the windows `[since + k·dt, since + (k+1)·dt)`, the sample at TPOS is the last
    /// window complete at the trigger, which ends `phase` s before it (0 ≤ phase < dt).
    fn fire(&mut self, now: Instant) {
        let Acq::Running { since, .. } = self.acq else {
            return;
        };
        let now = match self.src {
            Src::ExtPe | Src::ExtNe => self.ext.last_edge().map_or(now, |e| e.clamp(since, now)),
            _ => now,
        };
        let dt = self.dt();
        let e = (now - since).as_secs_f64();
        let written = (e / dt) as usize;
        self.phase_s = (e - written as f64 * dt).clamp(0.0, dt);
        self.tpos = (self.wpos0 + written + BUF - 1) % BUF;
        self.src = Src::Disabled;
        self.acq = Acq::Triggered {
            at: now,
            post: self.post_samples(),
        };
        self.record(now);
    }

    /// The time of sample j (j = 0 at TPOS) relative to the trigger, s: the middle of its
    /// averaging window with `ACQ:AVG ON` (`(j − ½)·dt − phase`), the window's last ADC sample
    /// without (`j·dt − phase`: decimation keeps one sample of each window).
    fn sample_time(&self, j: isize) -> f64 {
        let dt = self.dt();
        let mid = if self.avg { 0.5 * dt } else { 0.0 };
        j as f64 * dt - mid - self.phase_s
    }

    /// Fill the ring buffer for the trigger at `tpos` (instant `at`): samples up to TPOS were
    /// written before it, `post` more after it. Without a stage path every sample carries the
    /// signal at the position at the trigger; with one, sample j ≥ 0 (j = 0 at TPOS) carries
    /// the signal at the path's position at its time ([`Self::sample_time`]; the mean over a
    /// window of a signal varying linearly is its middle's value, and across a window of
    /// `v·dt` ≈ 2 nm the scene's curvature changes it by about 1e-6 of its peak).
    fn record(&mut self, at: Instant) {
        let base = self.input_volts();
        let path = self.cfg.path.as_ref().and_then(StagePath::get);
        let post_n = self.post_samples();
        // the volts per sample from TPOS on at the path's position at its time
        let moving: Option<Vec<[f64; 4]>> = path.map(|p| {
            let positions: Vec<crate::instrument::Pos> = (0..=post_n)
                .map(|j| {
                    let s = self.sample_time(j as isize);
                    let t = if s >= 0.0 {
                        at.checked_add(Duration::from_secs_f64(s))
                    } else {
                        at.checked_sub(Duration::from_secs_f64(-s))
                    };
                    match t {
                        Some(t) if t >= p.start => p.at_time((t - p.start).as_secs_f64()),
                        _ => p.base,
                    }
                })
                .collect();
            self.volts_along(&positions)
        });
        let post = self.post_samples();
        let sigma = if self.avg {
            self.cfg.noise_v / (self.dec as f64).sqrt()
        } else {
            self.cfg.noise_v
        };
        let normal = rand_distr::Normal::new(0.0, sigma.max(0.0)).ok();
        for ch in 0..self.cfg.inputs {
            let fs = if self.hv[ch] { 20.0 } else { 1.0 };
            for k in 0..BUF {
                // index k holds sample j = k − tpos (wrapped into −pre..=post)
                let mut j = (k + BUF - self.tpos) % BUF;
                if j > post {
                    j = j.wrapping_sub(BUF);
                }
                let t = self.sample_time(j as isize);
                let mut v = match &moving {
                    Some(m) if (j as isize) >= 0 && j < m.len() => m[j][ch],
                    _ => base[ch],
                };
                if let Some(g) = &self.cfg.generator {
                    v += g(t)[ch];
                }
                if let Some(n) = normal {
                    if sigma > 0.0 {
                        v += self.rng.sample(n);
                    }
                }
                self.data[ch][k] = v.clamp(-fs, fs) as f32;
            }
        }
    }

    /// Advance the acquisition to `now`: triggers, end of writing.
    fn update(&mut self) {
        let now = Instant::now();
        let no_trigger = lock(&self.faults).no_trigger;
        if let Acq::Running { ext_seen, .. } = self.acq {
            let fire = !no_trigger
                && match self.src {
                    Src::Now => true,
                    Src::ExtPe | Src::ExtNe => self.ext.count() > ext_seen,
                    Src::ChPe(c) | Src::ChNe(c) if c < self.cfg.inputs => {
                        let v = self.input_volts()[c];
                        let prev = self.last_level[c].replace(v);
                        match (self.src, prev) {
                            (Src::ChPe(_), Some(p)) => p < self.level_v && v >= self.level_v,
                            (Src::ChNe(_), Some(p)) => p > self.level_v && v <= self.level_v,
                            _ => false,
                        }
                    }
                    _ => false,
                };
            if fire {
                self.fire(now);
            }
        }
        if let Acq::Triggered { at, post } = self.acq {
            if self.elapsed_samples(at, now) >= post {
                self.wstop = (self.tpos + post + 1) % BUF;
                self.wpos0 = self.wstop;
                self.acq = Acq::Idle;
                // stays "filled" until the next start
                self.filled = true;
            }
        }
    }

    fn wpos(&self) -> usize {
        let now = Instant::now();
        match self.acq {
            Acq::Idle => self.wstop,
            Acq::Running { since, .. } => (self.wpos0 + self.elapsed_samples(since, now)) % BUF,
            Acq::Triggered { at, .. } => (self.tpos + 1 + self.elapsed_samples(at, now)) % BUF,
        }
    }

    /// `count` samples of input `ch` from buffer index `start` (wrapping), formatted.
    fn data_reply(&mut self, ch: usize, start: usize, count: usize) -> Reply {
        let vals: Vec<f32> = (0..count)
            .map(|i| self.data[ch][(start + i) % BUF])
            .collect();
        let fs = if self.hv[ch] { 20.0 } else { 1.0 };
        let counts = || {
            vals.iter()
                .map(|&v| ((v as f64 / fs * 8192.0).round() as i64).clamp(-8192, 8191) as i16)
        };
        match (self.binary, self.raw) {
            (false, false) => Reply::Text(format!(
                "{{{}}}",
                vals.iter()
                    .map(|v| format!("{v:.6}"))
                    .collect::<Vec<_>>()
                    .join(",")
            )),
            (false, true) => Reply::Text(format!(
                "{{{}}}",
                counts()
                    .map(|c| c.to_string())
                    .collect::<Vec<_>>()
                    .join(",")
            )),
            (true, raw) => {
                let mut body = Vec::new();
                if raw {
                    for c in counts() {
                        body.extend(if self.little_endian {
                            c.to_le_bytes()
                        } else {
                            c.to_be_bytes()
                        });
                    }
                } else {
                    for v in &vals {
                        body.extend(if self.little_endian {
                            v.to_le_bytes()
                        } else {
                            v.to_be_bytes()
                        });
                    }
                }
                let len = body.len().to_string();
                let mut out = format!("#{}{}", len.len(), len).into_bytes();
                out.extend(body);
                Reply::Bin(out)
            }
        }
    }

    fn reset(&mut self) {
        self.dec = 1;
        self.avg = true;
        self.src = Src::Disabled;
        self.level_v = 0.0;
        self.delay = 0;
        self.raw = false;
        self.acq = Acq::Idle;
    }

    /// `ACQ:SOUR<n>:…`: a command of input n (1-based), or error −113 for an input the
    /// board does not have.
    fn source_command(&mut self, rest: &str, arg: &str) -> Option<Reply> {
        let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
        let tail = &rest[digits.len()..];
        let ch = match digits.parse::<usize>() {
            Ok(n) if (1..=self.cfg.inputs).contains(&n) => n - 1,
            _ => {
                self.push_error(-113, "Undefined header");
                return None;
            }
        };
        self.channel_command(ch, tail, arg)
    }

    /// `ACQ:TRIG:LEV <v>[V|mV]`: the trigger level.
    fn set_trigger_level(&mut self, arg: &str) {
        let up = arg.to_ascii_uppercase();
        let (num, scale) = match up.strip_suffix("MV") {
            Some(n) => (n.trim(), 1e-3),
            None => (up.strip_suffix('V').unwrap_or(&up).trim(), 1.0),
        };
        match num.parse::<f64>() {
            Ok(v) if v.is_finite() => self.level_v = v * scale,
            _ if arg.is_empty() => self.push_error(-109, "Missing first parameter."),
            _ => self.push_error(-224, "Illegal parameter value"),
        }
    }

    /// Handle one command line.
    fn handle(&mut self, line: &str) -> Option<Reply> {
        self.update();
        let line = line.trim();
        let (head, arg) = match line.split_once(char::is_whitespace) {
            Some((h, a)) => (h, a.trim()),
            None => (line, ""),
        };
        let h = head.trim_start_matches(':').to_ascii_uppercase();
        let text = |s: String| Some(Reply::Text(s));
        let need_no_arg = |b: &mut Self| {
            if !arg.is_empty() {
                b.push_error(-108, "Parameter not allowed");
                false
            } else {
                true
            }
        };
        // channel commands: ACQ:SOUR<n>:...
        if let Some(rest) = h.strip_prefix("ACQ:SOUR") {
            return self.source_command(rest, arg);
        }
        match h.as_str() {
            "*IDN?" => need_no_arg(self).then(|| Reply::Text(self.cfg.idn.clone())),
            "*CLS" => {
                self.errors.clear();
                None
            }
            "*RST" => {
                self.reset();
                self.errors.clear();
                None
            }
            "*STB?" => text(if self.errors.is_empty() { "0" } else { "4" }.into()),
            "SYST:ERR?" | "SYST:ERR:NEXT?" | "SYSTEM:ERROR?" | "SYSTEM:ERROR:NEXT?" => {
                let (code, info) = self.errors.pop_front().unwrap_or((0, String::new()));
                let msg = error_text(code);
                text(if info.is_empty() || info == msg {
                    format!("{code},\"{msg}\"")
                } else {
                    format!("{code},\"{msg};{info}\"")
                })
            }
            "ACQ:START" => {
                self.acq = Acq::Running {
                    since: Instant::now(),
                    ext_seen: self.ext.count(),
                };
                self.filled = false;
                self.last_level = [None; 4];
                None
            }
            "ACQ:STOP" => {
                if !matches!(self.acq, Acq::Idle) {
                    self.wstop = self.wpos();
                    self.wpos0 = self.wstop;
                }
                self.acq = Acq::Idle;
                // stopping resets the write state machine, which clears the trigger source
                self.src = Src::Disabled;
                None
            }
            "ACQ:RST" => {
                self.reset();
                None
            }
            "ACQ:DEC" => {
                match arg.parse::<u32>() {
                    Ok(d) if d.is_power_of_two() && d <= 65536 => self.dec = d,
                    Ok(_) => self.push_error(-224, "Parameter decimation is invalid."),
                    Err(_) if arg.is_empty() => self.push_error(-109, "Missing first parameter."),
                    Err(_) => self.push_error(-224, "Parameter decimation is invalid."),
                }
                None
            }
            "ACQ:DEC?" => text(self.dec.to_string()),
            "ACQ:AVG" => {
                match arg.to_ascii_uppercase().as_str() {
                    "ON" => self.avg = true,
                    "OFF" => self.avg = false,
                    _ => self.push_error(-224, "Illegal parameter value"),
                }
                None
            }
            "ACQ:AVG?" => text(if self.avg { "ON" } else { "OFF" }.into()),
            "ACQ:TRIG" => {
                let a = arg.to_ascii_uppercase();
                match SOURCES.iter().find(|(n, _)| *n == a) {
                    Some((_, s)) => {
                        self.src = *s;
                        if let Acq::Running { .. } = self.acq {
                            self.update();
                        }
                    }
                    None if a.is_empty() => self.push_error(-109, "Missing first parameter."),
                    None => self.push_error(-224, "Illegal parameter value"),
                }
                None
            }
            "ACQ:TRIG:STAT?" => text(
                if self.src == Src::Disabled {
                    "TD"
                } else {
                    "WAIT"
                }
                .into(),
            ),
            "ACQ:TRIG:FILL?" => text(if self.filled { "1" } else { "0" }.into()),
            "ACQ:TRIG:DLY" => {
                match arg.parse::<i64>() {
                    Ok(d) if d.abs() <= 1 << 30 => self.delay = d,
                    _ if arg.is_empty() => self.push_error(-109, "Missing first parameter."),
                    _ => self.push_error(-224, "Illegal parameter value"),
                }
                None
            }
            "ACQ:TRIG:DLY?" => text(self.delay.to_string()),
            "ACQ:TRIG:LEV" => {
                self.set_trigger_level(arg);
                None
            }
            "ACQ:TRIG:LEV?" => text(format!("{:.6}", self.level_v)),
            "ACQ:WPOS?" => text(self.wpos().to_string()),
            "ACQ:TPOS?" => text(self.tpos.to_string()),
            "ACQ:BUF:SIZE?" => text(BUF.to_string()),
            "ACQ:DATA:UNITS" => {
                if let Some(v) = self.choice(arg, "RAW", "VOLTS") {
                    self.raw = v;
                }
                None
            }
            "ACQ:DATA:UNITS?" => text(if self.raw { "RAW" } else { "VOLTS" }.into()),
            "ACQ:DATA:FORMAT" => {
                if let Some(v) = self.choice(arg, "BIN", "ASCII") {
                    self.binary = v;
                }
                None
            }
            "ACQ:DATA:FORMAT?" => text(if self.binary { "BIN" } else { "ASCII" }.into()),
            "ACQ:DATA:BYTE:ORDER" => {
                if let Some(v) = self.choice(arg, "LEND", "BEND") {
                    self.little_endian = v;
                }
                None
            }
            _ => {
                self.push_error(-113, "Undefined header");
                None
            }
        }
    }

    /// A two-valued setting: `Some(true)` for `on`, `Some(false)` for `off` (either case);
    /// anything else queues error -224 and changes nothing.
    fn choice(&mut self, arg: &str, on: &str, off: &str) -> Option<bool> {
        let a = arg.to_ascii_uppercase();
        if a == on {
            Some(true)
        } else if a == off {
            Some(false)
        } else {
            self.push_error(-224, "Illegal parameter value");
            None
        }
    }

    fn channel_command(&mut self, ch: usize, tail: &str, arg: &str) -> Option<Reply> {
        let nums: Vec<Option<usize>> = if arg.is_empty() {
            vec![]
        } else {
            arg.split(',')
                .map(|s| s.trim().parse::<usize>().ok())
                .collect()
        };
        let want = |b: &mut Self, k: usize| -> Option<Vec<usize>> {
            if nums.len() != k || nums.iter().any(Option::is_none) {
                b.push_error(-109, "Missing or malformed parameter.");
                return None;
            }
            let v: Vec<usize> = nums.iter().map(|x| x.unwrap_or(0)).collect();
            if v.iter().any(|&x| x > BUF) {
                b.push_error(-222, "Data out of range");
                return None;
            }
            Some(v)
        };
        match tail {
            ":GAIN" => {
                match arg.to_ascii_uppercase().as_str() {
                    "LV" => self.hv[ch] = false,
                    "HV" => self.hv[ch] = true,
                    _ => self.push_error(-224, "Illegal parameter value"),
                }
                None
            }
            ":GAIN?" => Some(Reply::Text(if self.hv[ch] { "HV" } else { "LV" }.into())),
            ":DATA?" => {
                let start = self.wstop;
                Some(self.data_reply(ch, start, BUF))
            }
            ":DATA:STA:N?" | ":DATA:START:N?" => {
                let v = want(self, 2)?;
                if v[0] >= BUF {
                    self.push_error(-222, "Data out of range");
                    return None;
                }
                Some(self.data_reply(ch, v[0], v[1]))
            }
            ":DATA:STA:END?" | ":DATA:START:END?" => {
                let v = want(self, 2)?;
                if v[0] >= BUF || v[1] >= BUF {
                    self.push_error(-222, "Data out of range");
                    return None;
                }
                let n = (v[1] + BUF - v[0]) % BUF + 1;
                Some(self.data_reply(ch, v[0], n))
            }
            ":DATA:OLD:N?" => {
                let v = want(self, 1)?;
                let start = self.wstop;
                Some(self.data_reply(ch, start, v[0]))
            }
            ":DATA:LAT:N?" | ":DATA:LATEST:N?" => {
                let v = want(self, 1)?;
                let start = (self.wstop + BUF - v[0]) % BUF;
                Some(self.data_reply(ch, start, v[0]))
            }
            _ => {
                self.push_error(-113, "Undefined header");
                None
            }
        }
    }
}

/// Start a Red Pitaya emulator listening on `addr` (`127.0.0.1:0`: a free loopback port; the
/// emulator's path is `tcp://IP:PORT`), its inputs carrying `source` at the shared stage
/// `position`. Returns the emulator and its external trigger input.
pub fn start_redpitaya_emulator(
    cfg: RedPitayaEmulatorConfig,
    position: SharedPosition,
    source: impl SignalSource,
    addr: &str,
) -> std::io::Result<(Emulator, ExtTrigger)> {
    if !(cfg.inputs == 2 || cfg.inputs == 4) {
        return Err(std::io::Error::other(format!(
            "inputs {}: a STEMlab 125-14 has 2 fast inputs, its 4-input model 4",
            cfg.inputs
        )));
    }
    let listener = std::net::TcpListener::bind(addr)?;
    listener.set_nonblocking(true)?;
    let path = format!("tcp://{}", listener.local_addr()?);
    let faults = Arc::new(Mutex::new(cfg.faults.clone()));
    let ext = ExtTrigger::new();
    let board = Board::new(
        cfg,
        position.clone(),
        Box::new(source),
        ext.clone(),
        faults.clone(),
    );
    let f = faults.clone();
    let emu = launch("redpitaya", faults, position, path, move |h| {
        serve(listener, board, f, h)
    })?;
    Ok((emu, ext))
}

fn serve(
    listener: std::net::TcpListener,
    mut board: Board,
    faults: Arc<Mutex<Faults>>,
    h: crate::instrument::emulation::Served,
) {
    let mut client: Option<std::net::TcpStream> = None;
    let mut buf: Vec<u8> = Vec::new();
    let mut chunk = [0u8; 4096];
    'serve: while !h.stop.load(Ordering::SeqCst) {
        board.update();
        let Some(c) = client.as_mut() else {
            match listener.accept() {
                Ok((s, _)) => {
                    let _ = s.set_nonblocking(false);
                    let _ = s.set_read_timeout(Some(Duration::from_millis(5)));
                    let _ = s.set_nodelay(true);
                    client = Some(s);
                    buf.clear();
                    // a new connection has its own data format settings, as on the board
                    board.binary = false;
                    board.little_endian = false;
                }
                Err(_) => std::thread::sleep(Duration::from_millis(5)),
            }
            continue;
        };
        match c.read(&mut chunk) {
            Ok(0) => {
                client = None;
                continue;
            }
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock
                        | std::io::ErrorKind::TimedOut
                        | std::io::ErrorKind::Interrupted
                ) => {}
            Err(_) => {
                client = None;
                continue;
            }
        }
        while let Some(i) = buf.iter().position(|&b| b == b'\n') {
            let raw: Vec<u8> = buf.drain(..=i).collect();
            let line = String::from_utf8_lossy(&raw[..raw.len() - 1])
                .trim_end_matches('\r')
                .to_string();
            if line.trim().is_empty() {
                continue;
            }
            {
                let mut log = lock(&h.log);
                if log.len() >= LOG_CAP {
                    log.pop_front();
                }
                log.push_back(line.clone());
            }
            let (silent, inject, garble_it, last) = {
                let mut f = lock(&faults);
                let last = match f.unplug_after {
                    Some(n) => {
                        f.unplug_after = Some(n.saturating_sub(1));
                        n <= 1
                    }
                    None => false,
                };
                let is_err_q = line.to_ascii_uppercase().starts_with("SYST");
                let mut inject = if !is_err_q { f.error_next.take() } else { None };
                // `reject`: the (n+1)-th command with this first word fails with its code
                let first = line.split_whitespace().next().unwrap_or("");
                if let Some((word, n, code)) = f.reject.clone() {
                    if inject.is_none() && first.eq_ignore_ascii_case(&word) {
                        if n == 0 {
                            f.reject = None;
                            inject = Some(code);
                        } else {
                            f.reject = Some((word, n - 1, code));
                        }
                    }
                }
                let g = f.garble_replies > 0;
                (f.silent, inject, g, last)
            };
            let reply = match inject {
                Some(code) => {
                    board.push_error(code, "");
                    None
                }
                None => board.handle(&line),
            };
            if let (Some(r), false) = (reply, silent) {
                let mut bytes = match r {
                    Reply::Text(t) if garble_it => garble(&t),
                    Reply::Text(t) => t.into_bytes(),
                    Reply::Bin(mut b) if garble_it => {
                        b[0] = 0xFF;
                        b
                    }
                    Reply::Bin(b) => b,
                };
                if garble_it {
                    let mut f = lock(&faults);
                    f.garble_replies = f.garble_replies.saturating_sub(1);
                }
                bytes.extend_from_slice(b"\r\n");
                if let Some(c) = client.as_mut() {
                    if c.write_all(&bytes).and_then(|_| c.flush()).is_err() {
                        client = None;
                    }
                }
            }
            if last {
                std::thread::sleep(Duration::from_millis(50));
                break 'serve;
            }
        }
        if buf.len() > 1 << 16 {
            buf.clear();
        }
    }
    h.finished.store(true, Ordering::SeqCst);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn board(cfg: RedPitayaEmulatorConfig) -> Board {
        Board::new(
            cfg,
            crate::instrument::emulation::shared_position([0.1, 0.0, 0.0]),
            Box::new(crate::instrument::emulation::standin_bead),
            ExtTrigger::new(),
            Arc::new(Mutex::new(Faults::default())),
        )
    }

    fn text(r: Option<Reply>) -> String {
        match r {
            Some(Reply::Text(t)) => t,
            Some(Reply::Bin(_)) => panic!("binary"),
            None => panic!("no reply"),
        }
    }

    #[test]
    fn wrong_commands_queue_errors_and_get_no_reply() {
        let mut b = board(RedPitayaEmulatorConfig::default());
        assert!(b.handle("ACQ:BOGUS?").is_none());
        assert!(b.handle("ACQ:DEC 3").is_none());
        assert!(
            b.handle("ACQ:SOUR3:DATA?").is_none(),
            "2-input board has no IN3"
        );
        assert_eq!(text(b.handle("*STB?")), "4");
        assert_eq!(text(b.handle("SYST:ERR?")), "-113,\"Undefined header\"");
        assert_eq!(
            text(b.handle("SYST:ERR?")),
            "-224,\"Illegal parameter value;Parameter decimation is invalid.\""
        );
        assert_eq!(text(b.handle("SYST:ERR?")), "-113,\"Undefined header\"");
        assert_eq!(text(b.handle("SYST:ERR?")), "0,\"No error\"");
        assert_eq!(text(b.handle("ACQ:DEC?")), "1");
    }

    #[test]
    fn trigger_state_follows_the_source() {
        let mut b = board(RedPitayaEmulatorConfig::default());
        // before any trigger source: TD (disabled counts as triggered)
        assert_eq!(text(b.handle("ACQ:TRIG:STAT?")), "TD");
        b.handle("ACQ:START");
        b.handle("ACQ:TRIG EXT_PE");
        assert_eq!(text(b.handle("ACQ:TRIG:STAT?")), "WAIT");
        b.ext.pulse();
        assert_eq!(text(b.handle("ACQ:TRIG:STAT?")), "TD");
        // ASCII volts: x·exp(−x²/0.16) at x = 0.1 µm, within the 1 mV noise
        b.handle("ACQ:TRIG:DLY -8191");
        b.handle("ACQ:START");
        b.handle("ACQ:TRIG NOW");
        std::thread::sleep(Duration::from_millis(2));
        assert_eq!(text(b.handle("ACQ:TRIG:FILL?")), "1");
        let tpos: usize = text(b.handle("ACQ:TPOS?")).parse().unwrap();
        let r = text(b.handle(&format!("ACQ:SOUR1:DATA:STA:N? {tpos},1")));
        let v: f64 = r.trim_matches(|c| c == '{' || c == '}').parse().unwrap();
        let exact = 0.1 * (-0.01f64 / 0.16).exp();
        assert!((v - exact).abs() < 5e-3, "{r} vs {exact}");
        b.handle("ACQ:DATA:UNITS RAW");
        let r = text(b.handle(&format!("ACQ:SOUR1:DATA:STA:N? {tpos},1")));
        let c: i64 = r.trim_matches(|c| c == '{' || c == '}').parse().unwrap();
        assert!((c as f64 - exact * 8192.0).abs() < 50.0, "{r}");
    }
}
