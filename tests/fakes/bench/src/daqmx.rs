//! NI-DAQmx, as declared in `NIDAQmx.h` (NI's header; on 64-bit Linux with GCC `int32` is
//! `signed int` and `uInt32` `unsigned int`, as NI's current header's typedef block says;
//! `bool32` = `uInt32`, `TaskHandle` = `void*`, `float64` = `double`, `uInt64` =
//! `unsigned long long`; `__CFUNC` is empty on Linux: the C calling convention).
//!
//! The board: an NI PCI-6120 named `Dev1` (setting `daq_device`): four simultaneously
//! sampled 16-bit AI channels `ai0`–`ai3` at up to 800 kS/s each, input ranges ±42, ±20, ±10,
//! ±5, ±2, ±1, ±0.5, ±0.2 V; two 16-bit AO channels `ao0`, `ao1`, ±10 V, up to 4 MS/s (one
//! channel) or 2.5 MS/s (two). The AI range list and AO rates are from the S Series
//! specifications as remembered, not checked against a stored NI document.
//!
//! Wiring (setting `wiring`): ai0 = Sx, ai1 = Sy, ai2 = sum, ai3 = the x axis' sensor monitor;
//! ao0 → the x axis' external input, ao1 → y.
//!
//! Timing model (wall time). A task on the onboard clock started at t0 takes sample k at
//! t0 + k / rate. An AI task whose clock source is `/Dev1/ao/SampleClock` samples at the AO
//! task's sample clock edges (from the first edge after the AI task started; none before the
//! AO task starts, none after a finite AO generation ends or the AO task stops). A start
//! trigger `/Dev1/ao/StartTrigger` starts the AI task at the AO task's start, if the AI task
//! was started (armed) before; an AI task armed after the AO task started has missed the
//! trigger and never starts (reads time out, −200284), as on the board. A sample exists once
//! its time has passed; a read waits for its samples up to its timeout.
//!
//! Buffer model. A continuous AI task's buffer holds `B` samples per channel (the larger of
//! `sampsPerChan` and NI's default for the rate: 1 kS up to 100 S/s, 10 kS up to 10 kS/s,
//! 100 kS up to 1 MS/s; or `DAQmxCfgInputBuffer`). When the acquired samples not yet read
//! exceed `B`, the oldest were overwritten: the read returns −200279 (and so does every
//! later read until the task is restarted). A finite task's buffer holds all its samples.
//!
//! A continuous AO task with regeneration off (`DAQmxSetWriteRegenMode`) plays each sample
//! written once; a clock edge that finds no sample written stops the generation and its sample
//! clock (AI on that clock takes no more samples), and the task's next write returns −200290
//! until it is restarted. Its buffer holds `DAQmxCfgOutputBuffer`'s samples per channel, or as
//! many as were written before the start: a write that finds less space than it brings
//! waits (the caller's thread blocked) until the generation has played enough, up to its
//! timeout, then fails with −200292 and writes nothing; `DAQmxGetWriteSpaceAvail` tells the
//! space free now.
//!
//! An AO channel holds the last value it generated when its task stops or is cleared;
//! `DAQmxResetDevice` sets both AO channels to 0 V (and aborts the device's tasks).

use crate::config::AiSource;
use crate::errors::*;
use crate::{cstr, guard, now, put_cstr, sleep_until, with_bench, Bench, Config};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use std::collections::BTreeMap;
use std::os::raw::{c_char, c_void};

#[allow(non_camel_case_types)]
pub type int32 = i32;
#[allow(non_camel_case_types)]
pub type uInt32 = u32;
#[allow(non_camel_case_types)]
pub type uInt64 = u64;
#[allow(non_camel_case_types)]
pub type float64 = f64;
#[allow(non_camel_case_types)]
pub type bool32 = u32;
pub type TaskHandle = *mut c_void;

// NIDAQmx.h values
pub const VAL_VOLTS: i32 = 10348;
pub const VAL_FROM_CUSTOM_SCALE: i32 = 10065;
pub const VAL_RISING: i32 = 10280;
pub const VAL_FALLING: i32 = 10171;
pub const VAL_FINITE_SAMPS: i32 = 10178;
pub const VAL_CONT_SAMPS: i32 = 10123;
pub const VAL_HW_TIMED_SINGLE_POINT: i32 = 12522;
pub const VAL_GROUP_BY_CHANNEL: u32 = 0;
pub const VAL_GROUP_BY_SCAN_NUMBER: u32 = 1;
pub const VAL_CFG_DEFAULT: i32 = -1;
pub const VAL_DIFF: i32 = 10106;
pub const VAL_RSE: i32 = 10083;
pub const VAL_NRSE: i32 = 10078;
pub const VAL_PSEUDO_DIFF: i32 = 12529;
pub const VAL_AUTO: i32 = -1;
pub const VAL_WAIT_INFINITELY: f64 = -1.0;
pub const VAL_ALLOW_REGEN: i32 = 10097;
pub const VAL_DO_NOT_ALLOW_REGEN: i32 = 10158;
/// Read.WaitMode values (`DAQmx_Val_WaitForInterrupt`, `_Poll`, `_Yield`, `_Sleep`).
pub const VAL_WAIT_FOR_INTERRUPT: i32 = 12523;
pub const VAL_POLL: i32 = 12524;
pub const VAL_YIELD: i32 = 12525;
pub const VAL_SLEEP: i32 = 12547;
pub const VAL_TASK_START: i32 = 0;
pub const VAL_TASK_STOP: i32 = 1;
pub const VAL_TASK_VERIFY: i32 = 2;
pub const VAL_TASK_COMMIT: i32 = 3;
pub const VAL_TASK_RESERVE: i32 = 4;
pub const VAL_TASK_UNRESERVE: i32 = 5;
pub const VAL_TASK_ABORT: i32 = 6;

/// The PCI-6120's numbers.
pub const PRODUCT_TYPE: &str = "PCI-6120";
pub const AI_CHANNELS: usize = 4;
pub const AO_CHANNELS: usize = 2;
pub const AI_MAX_RATE: f64 = 800e3;
pub const AO_MAX_RATE_1: f64 = 4e6;
pub const AO_MAX_RATE_2: f64 = 2.5e6;
pub const AI_RANGES: [f64; 8] = [0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 42.0];
pub const AO_RANGE: f64 = 10.0;

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Kind {
    Ai,
    Ao,
}

#[derive(Debug, Clone)]
pub struct Chan {
    pub phys: usize,
    pub name: String,
    pub min: f64,
    pub max: f64,
    /// AI: the input range chosen (± V).
    pub range: f64,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Clock {
    Onboard,
    AoSampleClock,
    /// An external terminal nothing drives here (never ticks).
    External,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Timing {
    pub clock: Clock,
    pub rate: f64,
    /// Finite: samples per channel; None: continuous.
    pub finite: Option<u64>,
    pub samps_per_chan: u64,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Trigger {
    AoStart,
    External,
}

/// One task.
#[derive(Debug, Clone)]
pub struct Task {
    pub name: String,
    pub kind: Option<Kind>,
    pub chans: Vec<Chan>,
    pub timing: Option<Timing>,
    pub trigger: Option<Trigger>,
    pub input_buf: Option<u64>,
    pub regen: bool,
    /// Read.WaitMode (`DAQmxSetReadWaitMode`): [`VAL_POLL`] checks for the samples as fast
    /// as it can (here: a busy wait); the others sleep between checks.
    pub wait_mode: i32,
    pub running: bool,
    /// Bench time of the start (AI: when armed).
    pub t_start: f64,
    /// AI: samples per channel read so far.
    pub read_pos: u64,
    /// AI: the reader fell behind (every read fails until a restart).
    pub overflowed: bool,
    /// AO: the buffer (per channel) and pending on-demand values.
    pub ao_buf: Vec<Vec<f64>>,
    pub ao_pending: Option<Vec<f64>>,
    /// AO timed: the buffer's size per channel (`DAQmxCfgOutputBuffer`, or the first write
    /// before the start).
    pub ao_cap: Option<u64>,
    /// AO continuous without regeneration: a clock edge came with no sample written (the
    /// generation stopped, −200290 from then on until the task is restarted).
    pub underflow: bool,
    /// AO without regeneration: the samples before this one were played and dropped from
    /// `ao_buf` (a stream's buffer does not grow with the stream).
    pub ao_base: u64,
    /// AO timed: the first clock edge, the samples applied so far.
    pub ao_t0: f64,
    pub ao_next: u64,
    /// The read started the task (DAQmx's implicit start).
    pub implicit_start: bool,
}

impl Task {
    fn new(name: String) -> Self {
        Task {
            name,
            kind: None,
            chans: Vec::new(),
            timing: None,
            trigger: None,
            input_buf: None,
            regen: true,
            wait_mode: VAL_YIELD,
            running: false,
            t_start: 0.0,
            read_pos: 0,
            overflowed: false,
            underflow: false,
            ao_base: 0,
            ao_buf: Vec::new(),
            ao_pending: None,
            ao_cap: None,
            ao_t0: 0.0,
            ao_next: 0,
            implicit_start: false,
        }
    }

    /// The continuous AI buffer size per channel (see the module documentation).
    pub fn buffer_size(&self) -> u64 {
        let t = self.timing.expect("timed task");
        if let Some(n) = t.finite {
            return n;
        }
        if let Some(b) = self.input_buf {
            return b;
        }
        let default = if t.rate <= 100.0 {
            1_000
        } else if t.rate <= 10_000.0 {
            10_000
        } else if t.rate <= 1_000_000.0 {
            100_000
        } else {
            1_000_000
        };
        t.samps_per_chan.max(default)
    }
}

/// The clock of the running (or last) timed AO generation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AoClock {
    pub t0: f64,
    pub dt: f64,
    /// Edges at times < `end` only.
    pub end: f64,
}

/// The board.
pub struct Board {
    pub device: String,
    pub serial: u32,
    pub tasks: BTreeMap<usize, Task>,
    next_id: usize,
    unnamed: usize,
    /// Voltage at each AO terminal.
    pub ao_v: [f64; AO_CHANNELS],
    pub ao_clock: Option<AoClock>,
    /// The AO task's start (for start triggers), and the task id.
    pub ao_start: Option<(f64, usize)>,
    pub reads: u64,
    pub removed: bool,
    pub last_error: Option<(i32, String)>,
    rng: ChaCha8Rng,
}

impl Board {
    pub fn new(cfg: &Config) -> Self {
        Board {
            device: cfg.daq_device.clone(),
            serial: cfg.daq_serial,
            tasks: BTreeMap::new(),
            next_id: 0,
            unnamed: 0,
            ao_v: [0.0; AO_CHANNELS],
            ao_clock: None,
            ao_start: None,
            reads: 0,
            removed: false,
            last_error: None,
            rng: ChaCha8Rng::seed_from_u64(cfg.seed ^ 0xDA0_6120),
        }
    }
}

fn handle_of(id: usize) -> TaskHandle {
    (0x1000 + id * 16) as TaskHandle
}

fn id_of(h: TaskHandle) -> usize {
    (h as usize).wrapping_sub(0x1000) / 16
}

/// A DAQmx error: the code and the extended text's details.
struct Fail(i32, String);

type R<T> = Result<T, Fail>;

fn fail<T>(code: i32, detail: impl Into<String>) -> R<T> {
    Err(Fail(code, detail.into()))
}

/// Record `r` as the last error (with the task's name) and return its code.
fn finish(b: &mut Bench, call: String, task: Option<&str>, r: R<()>) -> i32 {
    match r {
        Ok(()) => {
            b.log(format!("{call} -> 0"));
            0
        }
        Err(Fail(code, detail)) => {
            let mut text = daqmx_text(code).to_string();
            if !detail.is_empty() {
                text.push('\n');
                text.push_str(&detail);
            }
            if let Some(t) = task {
                text.push_str(&format!("\n\nTask Name: {t}"));
            }
            text.push_str(&format!("\n\nStatus Code: {code}"));
            b.daq.last_error = Some((code, text));
            b.log(format!("{call} -> {code}"));
            code
        }
    }
}

fn task_name(b: &Bench, h: TaskHandle) -> Option<String> {
    b.daq.tasks.get(&id_of(h)).map(|t| t.name.clone())
}

fn task_mut(b: &mut Bench, h: TaskHandle) -> R<&mut Task> {
    if h.is_null() {
        return fail(INVALID_TASK, "");
    }
    match b.daq.tasks.get_mut(&id_of(h)) {
        Some(t) => Ok(t),
        None => fail(INVALID_TASK, ""),
    }
}

fn device_ok(b: &Bench, dev: &str) -> R<()> {
    if b.cfg.faults.daq_missing || !dev.eq_ignore_ascii_case(&b.daq.device) {
        return fail(INVALID_DEVICE_ID, format!("Device Specified: {dev}"));
    }
    if b.daq.removed {
        return fail(DEV_CANNOT_BE_ACCESSED, format!("Device: {dev}"));
    }
    Ok(())
}

/// Parse a physical channel list (`Dev1/ai0:3, Dev1/ao1`, leading `/` allowed) into
/// (device, kind, index) triples.
fn parse_phys(b: &Bench, list: &str, want: Kind) -> R<Vec<usize>> {
    let mut out = Vec::new();
    let items: Vec<&str> = list
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .collect();
    if items.is_empty() {
        return fail(PHYS_CHAN_NOT_SPECIFIED, "");
    }
    for item in items {
        let item = item.trim_start_matches('/');
        let Some((dev, chan)) = item.split_once('/') else {
            return fail(
                PHYSICAL_CHAN_DOES_NOT_EXIST,
                format!("Physical Channel Name: {item}"),
            );
        };
        device_ok(b, dev)?;
        let lower = chan.to_ascii_lowercase();
        let (kind, rest) = if let Some(r) = lower.strip_prefix("ai") {
            (Kind::Ai, r)
        } else if let Some(r) = lower.strip_prefix("ao") {
            (Kind::Ao, r)
        } else {
            return fail(
                PHYSICAL_CHAN_DOES_NOT_EXIST,
                format!(
                    "Physical Channel Name: {chan}\n\nValid Physical Channels:\nai0:{}, ao0:{}\nDevice: {dev}",
                    AI_CHANNELS - 1,
                    AO_CHANNELS - 1
                ),
            );
        };
        let n = if kind == Kind::Ai {
            AI_CHANNELS
        } else {
            AO_CHANNELS
        };
        let bad = || {
            Fail(
                PHYSICAL_CHAN_DOES_NOT_EXIST,
                format!(
                    "Physical Channel Name: {chan}\n\nValid Physical Channels:\nai0:{}, ao0:{}\nDevice: {dev}",
                    AI_CHANNELS - 1,
                    AO_CHANNELS - 1
                ),
            )
        };
        let (a, z) = match rest.split_once(':') {
            Some((a, z)) => (a.parse::<usize>(), z.parse::<usize>()),
            None => (rest.parse::<usize>(), rest.parse::<usize>()),
        };
        let (Ok(a), Ok(z)) = (a, z) else {
            return Err(bad());
        };
        if a >= n || z >= n {
            return Err(bad());
        }
        if kind != want {
            return fail(
                INVALID_PHYS_CHAN_TYPE,
                format!("Physical Channel Name: {chan}\nDevice: {dev}"),
            );
        }
        let range: Vec<usize> = if a <= z {
            (a..=z).collect()
        } else {
            (z..=a).rev().collect()
        };
        out.extend(range);
    }
    Ok(out)
}

fn fmt_v(x: f64) -> String {
    format!("{x:e}")
}

// The channel-creation functions' own argument list (NIDAQmx.h), plus the bench and the kind.
#[allow(clippy::too_many_arguments)]
fn add_chans(
    b: &mut Bench,
    h: TaskHandle,
    phys: &str,
    name: &str,
    kind: Kind,
    term: i32,
    min: f64,
    max: f64,
    units: i32,
) -> R<()> {
    task_mut(b, h)?;
    let idx = parse_phys(b, phys, kind)?;
    let prop = |p: &str| {
        if kind == Kind::Ai {
            format!("DAQmx_AI_{p}")
        } else {
            format!("DAQmx_AO_{p}")
        }
    };
    if !(min.is_finite() && max.is_finite()) || min >= max {
        return fail(
            MIN_NOT_LESS_THAN_MAX,
            format!(
                "Property: {}\nRequested Value: {}\nProperty: {}\nRequested Value: {}",
                prop("Min"),
                fmt_v(min),
                prop("Max"),
                fmt_v(max)
            ),
        );
    }
    if units != VAL_VOLTS {
        return fail(
            INVALID_ATTRIBUTE_VALUE,
            format!(
                "Property: {}\nRequested Value: {units}\nYou Can Select: DAQmx_Val_Volts",
                prop("Voltage_Units")
            ),
        );
    }
    let range = match kind {
        Kind::Ai => {
            if ![VAL_CFG_DEFAULT, VAL_DIFF, VAL_PSEUDO_DIFF].contains(&term) {
                let name = match term {
                    VAL_RSE => "DAQmx_Val_RSE".to_string(),
                    VAL_NRSE => "DAQmx_Val_NRSE".to_string(),
                    t => t.to_string(),
                };
                return fail(
                    INVALID_ATTRIBUTE_VALUE,
                    format!("Property: DAQmx_AI_TermCfg\nRequested Value: {name}\nYou Can Select: DAQmx_Val_Diff, DAQmx_Val_PseudoDiff"),
                );
            }
            let need = max.abs().max(min.abs());
            match AI_RANGES.iter().find(|&&r| r >= need) {
                Some(&r) => r,
                None => {
                    let (p, v) = if max.abs() >= min.abs() {
                        ("Max", max)
                    } else {
                        ("Min", min)
                    };
                    return fail(
                        INVALID_ATTRIBUTE_VALUE,
                        format!(
                            "Property: DAQmx_AI_{p}\nRequested Value: {}\nMaximum Value: {}\nMinimum Value: {}",
                            fmt_v(v),
                            fmt_v(42.0),
                            fmt_v(-42.0)
                        ),
                    );
                }
            }
        }
        Kind::Ao => {
            if max > AO_RANGE || min < -AO_RANGE {
                let (p, v) = if max > AO_RANGE {
                    ("Max", max)
                } else {
                    ("Min", min)
                };
                return fail(
                    INVALID_ATTRIBUTE_VALUE,
                    format!(
                        "Property: DAQmx_AO_{p}\nRequested Value: {}\nMaximum Value: {}\nMinimum Value: {}",
                        fmt_v(v),
                        fmt_v(AO_RANGE),
                        fmt_v(-AO_RANGE)
                    ),
                );
            }
            AO_RANGE
        }
    };
    let dev = b.daq.device.clone();
    let t = task_mut(b, h)?;
    if t.running {
        return fail(OP_WHILE_TASK_RUNNING, "");
    }
    if t.kind.is_some() && t.kind != Some(kind) {
        return fail(MULTI_CHAN_TYPES_IN_TASK, "");
    }
    let names: Vec<String> = name
        .split(',')
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .collect();
    for (k, &p) in idx.iter().enumerate() {
        let prefix = if kind == Kind::Ai { "ai" } else { "ao" };
        let cname = match (names.len(), names.get(k)) {
            (1, _) if idx.len() > 1 => format!("{}{k}", names[0]),
            (_, Some(n)) => n.clone(),
            _ => format!("{dev}/{prefix}{p}"),
        };
        if t.chans.iter().any(|c| c.name == cname) {
            return fail(DUPLICATE_CHANNEL, format!("Virtual Channel Name: {cname}"));
        }
        t.chans.push(Chan {
            phys: p,
            name: cname,
            min,
            max,
            range,
        });
    }
    t.kind = Some(kind);
    if kind == Kind::Ao {
        t.ao_buf = vec![Vec::new(); t.chans.len()];
    }
    Ok(())
}

/// Advance everything that plays by itself (a timed AO generation, a Madlib load waveform)
/// to bench time `t`, applying its samples to the AO terminals and the stage in time order.
pub fn sync(b: &mut Bench, t: f64) {
    enum Ev {
        Ao(usize, f64),
        Usb(usize, f64),
    }
    let mut evs: Vec<(f64, Ev)> = Vec::new();
    // timed AO
    let mut underflow_at = None;
    if let Some((_, id)) = b.daq.ao_start {
        if let (Some(task), Some(clk)) = (b.daq.tasks.get_mut(&id), b.daq.ao_clock) {
            if task.running && task.kind == Some(Kind::Ao) {
                let timing = task.timing.expect("timed AO");
                let stream = !task.regen && timing.finite.is_none();
                let base = if stream { task.ao_base } else { 0 };
                let len = base + task.ao_buf.first().map_or(0, Vec::len) as u64;
                // one sample per pass until the clock, the finite count or the buffer ends
                while len > 0 && task.ao_next < timing.finite.unwrap_or(u64::MAX) {
                    let k = task.ao_next;
                    let tk = clk.t0 + k as f64 * clk.dt;
                    if tk > t || tk >= clk.end {
                        break;
                    }
                    if !task.regen && timing.finite.is_none() && k >= len {
                        // the clock edge came and no sample was written: the board stops
                        // the generation (and its sample clock) rather than play old data
                        task.underflow = true;
                        underflow_at = Some(tk);
                        break;
                    }
                    let i = if stream { k - base } else { k % len } as usize;
                    for (c, ch) in task.chans.iter().enumerate() {
                        evs.push((tk, Ev::Ao(ch.phys, task.ao_buf[c][i])));
                    }
                    task.ao_next += 1;
                }
                if stream && task.ao_next - task.ao_base >= 1 << 16 {
                    let played = (task.ao_next - task.ao_base) as usize;
                    for buf in task.ao_buf.iter_mut() {
                        buf.drain(..played.min(buf.len()));
                    }
                    task.ao_base = task.ao_next;
                }
            }
        }
    }
    if let (Some(t_end), Some(c)) = (underflow_at, b.daq.ao_clock.as_mut()) {
        c.end = c.end.min(t_end);
    }
    // Madlib load waveforms
    for w in b.mcl.playing.iter_mut() {
        while w.next < w.data.len() {
            let tk = w.t0 + w.next as f64 * w.dt;
            if tk > t {
                break;
            }
            evs.push((tk, Ev::Usb(w.axis, w.data[w.next])));
            w.next += 1;
        }
    }
    b.mcl.playing.retain(|w| w.next < w.data.len());
    evs.sort_by(|a, b| a.0.total_cmp(&b.0));
    for (tk, e) in evs {
        match e {
            Ev::Ao(ch, v) => set_ao(b, ch, tk, v),
            Ev::Usb(axis, um) => b.stage.command(axis, tk, um),
        }
    }
}

/// The AO terminal `ch` at `v` volts from `t` on (and the external input it is wired to).
fn set_ao(b: &mut Bench, ch: usize, t: f64, v: f64) {
    b.daq.ao_v[ch] = v;
    if let Some(axis) = b.cfg.ao[ch] {
        b.stage.external(axis, t, v);
    }
}

/// The clock of an AI task: (first sample time, period, number of samples that exist at
/// most, the clock's end). `None`: not ticking yet (or never).
fn ai_clock(b: &Bench, task: &Task) -> Option<(f64, f64, Option<u64>, f64)> {
    if b.cfg.faults.read_timeout {
        return None;
    }
    let timing = task.timing?;
    let finite = timing.finite;
    // the start: at arming, or at the AO start trigger if armed before it
    let start = match task.trigger {
        None => task.t_start,
        Some(Trigger::External) => return None,
        Some(Trigger::AoStart) => match b.daq.ao_start {
            Some((t_ao, _)) if t_ao >= task.t_start => t_ao,
            _ => return None,
        },
    };
    match timing.clock {
        Clock::External => None,
        Clock::Onboard => Some((start, 1.0 / timing.rate, finite, f64::INFINITY)),
        Clock::AoSampleClock => {
            let clk = b.daq.ao_clock?;
            if clk.t0 + 1e-12 < start && task.trigger.is_some() {
                // the AO clock started before this task was triggered (another generation)
                return None;
            }
            let k0 = ((start - clk.t0) / clk.dt - 1e-9).ceil().max(0.0);
            Some((clk.t0 + k0 * clk.dt, clk.dt, finite, clk.end))
        }
    }
}

/// Samples per channel that exist at time `t` (acquired so far).
fn acquired(clock: (f64, f64, Option<u64>, f64), t: f64) -> u64 {
    let (t0, dt, finite, end) = clock;
    if t < t0 {
        return 0;
    }
    // edges k with t0 + k·dt ≤ t, and with t0 + k·dt < end (the clock's end)
    let mut n = ((t - t0) / dt + 1e-9).floor() as u64 + 1;
    if end.is_finite() {
        let edges = ((end - t0) / dt - 1e-9).ceil().max(0.0) as u64;
        n = n.min(edges);
    }
    if let Some(f) = finite {
        n = n.min(f);
    }
    n
}

/// The voltage channel `ch` of an AI task reads at time `t` (given the signal there).
fn ai_volts(b: &mut Bench, src: AiSource, sig: [f64; 3], t: f64) -> f64 {
    match src {
        AiSource::Sx => b.cfg.qpd_gain_v * sig[0],
        AiSource::Sy => b.cfg.qpd_gain_v * sig[1],
        AiSource::Sum => b.cfg.sum_v * (1.0 + sig[2]),
        AiSource::Monitor(a) => b.stage.monitor_v(a, t),
        AiSource::Open => 0.0,
    }
}

/// Fill `out` with samples `from..from+n` of the task `id` (layout as DAQmx's fillMode).
fn produce(
    b: &mut Bench,
    id: usize,
    clock: (f64, f64, Option<u64>, f64),
    from: u64,
    n: u64,
    by_scan: bool,
    out: &mut [f64],
) {
    let chans: Vec<(usize, f64)> = b.daq.tasks[&id]
        .chans
        .iter()
        .map(|c| (c.phys, c.range))
        .collect();
    let nch = chans.len();
    let sigma = b.cfg.detector_noise_v;
    let noise = Normal::new(0.0, sigma.max(1e-300)).expect("finite σ");
    let needs_qpd = chans
        .iter()
        .any(|&(p, _)| matches!(b.cfg.ai[p], AiSource::Sx | AiSource::Sy | AiSource::Sum));
    for k in 0..n {
        let t = clock.0 + (from + k) as f64 * clock.1;
        let sig = if needs_qpd {
            let p = b.stage.position(t);
            b.qpd.signal(p)
        } else {
            [0.0; 3]
        };
        for (c, &(phys, range)) in chans.iter().enumerate() {
            let src = b.cfg.ai[phys];
            let mut v = ai_volts(b, src, sig, t);
            if sigma > 0.0 {
                v += noise.sample(&mut b.daq.rng);
            }
            // the 16-bit ADC: clipped to the range, quantised to 2·range / 65536
            let step = 2.0 * range / 65536.0;
            v = ((v / step).round() * step).clamp(-range, range - step);
            let idx = if by_scan {
                k as usize * nch + c
            } else {
                c * n as usize + k as usize
            };
            out[idx] = v;
        }
    }
}

fn start_task(b: &mut Bench, id: usize, implicit: bool) -> R<()> {
    let t = now();
    sync(b, t);
    if b.daq.removed {
        let dev = b.daq.device.clone();
        return fail(DEV_CANNOT_BE_ACCESSED, format!("Device: {dev}"));
    }
    let task = b.daq.tasks.get(&id).expect("checked");
    if task.running {
        return Ok(());
    }
    let kind = task.kind.ok_or(Fail(NO_CHANS_IN_TASK, String::new()))?;
    let timed = task.timing;
    // one task per subsystem at a time (the board has one AI and one AO timing engine)
    let busy = b.daq.tasks.iter().any(|(&k, o)| {
        k != id && o.running && o.kind == Some(kind) && (o.timing.is_some() || timed.is_some())
    });
    if busy {
        return fail(RESOURCE_RESERVED, format!("Device: {}", b.daq.device));
    }
    if kind == Kind::Ao {
        if let Some(tm) = timed {
            let max = if task.chans.len() > 1 {
                AO_MAX_RATE_2
            } else {
                AO_MAX_RATE_1
            };
            if tm.rate > max {
                return fail(
                    INVALID_ATTRIBUTE_VALUE,
                    format!(
                        "Property: DAQmx_SampClk_Rate\nRequested Value: {}\nValid Values Begin with: {}\nValid Values End with: {}",
                        fmt_v(tm.rate),
                        fmt_v(1e-3),
                        fmt_v(max)
                    ),
                );
            }
            if task.ao_buf.first().is_none_or(Vec::is_empty) {
                return fail(OUTPUT_BUFFER_EMPTY, "");
            }
        }
    }
    let t = if kind == Kind::Ai
        && task.chans.iter().any(|c| {
            matches!(
                b.cfg.ai[c.phys],
                AiSource::Sx | AiSource::Sy | AiSource::Sum
            )
        }) {
        // the scene's renderer is built here, before the acquisition starts, not in its first read
        let _ = b.qpd.renderer();
        now()
    } else {
        t
    };
    let task = b.daq.tasks.get_mut(&id).expect("checked");
    task.running = true;
    task.t_start = t;
    task.read_pos = 0;
    task.overflowed = false;
    task.underflow = false;
    task.implicit_start = implicit;
    if kind == Kind::Ao {
        match timed {
            Some(tm) => {
                task.ao_t0 = t;
                task.ao_next = 0;
                task.ao_base = 0;
                let end = match tm.finite {
                    Some(n) => t + n as f64 / tm.rate,
                    None => f64::INFINITY,
                };
                b.daq.ao_clock = Some(AoClock {
                    t0: t,
                    dt: 1.0 / tm.rate,
                    end,
                });
                b.daq.ao_start = Some((t, id));
            }
            None => {
                if let Some(vals) = task.ao_pending.take() {
                    let phys: Vec<usize> = task.chans.iter().map(|c| c.phys).collect();
                    for (p, v) in phys.into_iter().zip(vals) {
                        set_ao(b, p, t, v);
                    }
                }
            }
        }
    }
    Ok(())
}

fn stop_task(b: &mut Bench, id: usize) {
    let t = now();
    sync(b, t);
    if let Some(task) = b.daq.tasks.get_mut(&id) {
        if task.running && task.kind == Some(Kind::Ao) && task.timing.is_some() {
            if let Some(c) = b.daq.ao_clock.as_mut() {
                if b.daq.ao_start.map(|s| s.1) == Some(id) {
                    c.end = c.end.min(t);
                }
            }
        }
        task.running = false;
    }
}

// ---------------------------------------------------------------- exports: tasks

/// # Safety
/// `task_name` is NULL or a C string; `task_handle` points to a `TaskHandle`.
#[no_mangle]
pub unsafe extern "C" fn DAQmxCreateTask(
    task_name: *const c_char,
    task_handle: *mut TaskHandle,
) -> int32 {
    guard(-1, || {
        let name = cstr(task_name);
        with_bench(|b| {
            let r = (|| {
                if task_handle.is_null() {
                    return fail(NULL_PTR, "");
                }
                let name = if name.is_empty() {
                    let n = format!("_unnamedTask<{}>", b.daq.unnamed);
                    b.daq.unnamed += 1;
                    n
                } else {
                    if b.daq.tasks.values().any(|t| t.name == name) {
                        return fail(DUPLICATE_TASK, format!("Task Name: {name}"));
                    }
                    name.clone()
                };
                let id = b.daq.next_id;
                b.daq.next_id += 1;
                b.daq.tasks.insert(id, Task::new(name));
                *task_handle = handle_of(id);
                Ok(())
            })();
            let h = if task_handle.is_null() {
                0
            } else {
                *task_handle as usize
            };
            finish(
                b,
                format!("DAQmxCreateTask(taskName=\"{name}\") [handle {h:#x}]"),
                None,
                r,
            )
        })
    })
}

#[no_mangle]
pub extern "C" fn DAQmxClearTask(task_handle: TaskHandle) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let name = task_name(b, task_handle);
            let r = task_mut(b, task_handle).map(|_| ());
            if r.is_ok() {
                let id = id_of(task_handle);
                stop_task(b, id);
                b.daq.tasks.remove(&id);
            }
            finish(
                b,
                format!(
                    "DAQmxClearTask({})",
                    name.clone()
                        .unwrap_or(format!("{:#x}", task_handle as usize))
                ),
                name.as_deref(),
                r,
            )
        })
    })
}

#[no_mangle]
pub extern "C" fn DAQmxStartTask(task_handle: TaskHandle) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let name = task_name(b, task_handle);
            let r = task_mut(b, task_handle)
                .map(|_| ())
                .and_then(|_| start_task(b, id_of(task_handle), false));
            finish(
                b,
                format!("DAQmxStartTask({})", name.clone().unwrap_or_default()),
                name.as_deref(),
                r,
            )
        })
    })
}

#[no_mangle]
pub extern "C" fn DAQmxStopTask(task_handle: TaskHandle) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let name = task_name(b, task_handle);
            let r = task_mut(b, task_handle).map(|_| ());
            if r.is_ok() {
                stop_task(b, id_of(task_handle));
            }
            finish(
                b,
                format!("DAQmxStopTask({})", name.clone().unwrap_or_default()),
                name.as_deref(),
                r,
            )
        })
    })
}

#[no_mangle]
pub extern "C" fn DAQmxTaskControl(task_handle: TaskHandle, action: int32) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let name = task_name(b, task_handle);
            let r = task_mut(b, task_handle).map(|_| ()).and_then(|_| {
                let id = id_of(task_handle);
                match action {
                    VAL_TASK_START => start_task(b, id, false),
                    VAL_TASK_STOP | VAL_TASK_ABORT | VAL_TASK_UNRESERVE => {
                        stop_task(b, id);
                        Ok(())
                    }
                    VAL_TASK_VERIFY | VAL_TASK_COMMIT | VAL_TASK_RESERVE => Ok(()),
                    _ => fail(
                        INVALID_ATTRIBUTE_VALUE,
                        format!("Property: action\nRequested Value: {action}"),
                    ),
                }
            });
            finish(
                b,
                format!(
                    "DAQmxTaskControl({}, action={action})",
                    name.clone().unwrap_or_default()
                ),
                name.as_deref(),
                r,
            )
        })
    })
}

/// # Safety
/// `is_task_done` points to a `bool32`.
#[no_mangle]
pub unsafe extern "C" fn DAQmxIsTaskDone(
    task_handle: TaskHandle,
    is_task_done: *mut bool32,
) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let t = now();
            sync(b, t);
            let name = task_name(b, task_handle);
            let r = done(b, task_handle, t).and_then(|d| {
                if is_task_done.is_null() {
                    return fail(NULL_PTR, "");
                }
                *is_task_done = u32::from(d);
                Ok(())
            });
            finish(
                b,
                format!("DAQmxIsTaskDone({})", name.clone().unwrap_or_default()),
                name.as_deref(),
                r,
            )
        })
    })
}

/// Whether the task is done at `t` (a finite task that has acquired or generated all its
/// samples, or a task not running).
fn done(b: &mut Bench, h: TaskHandle, t: f64) -> R<bool> {
    let task = task_mut(b, h)?.clone();
    if !task.running {
        return Ok(true);
    }
    let Some(tm) = task.timing else {
        return Ok(true);
    };
    let Some(n) = tm.finite else {
        return Ok(false);
    };
    Ok(match task.kind {
        Some(Kind::Ao) => b.daq.ao_clock.is_some_and(|c| t >= c.t0 + n as f64 * c.dt),
        _ => ai_clock(b, &task).is_some_and(|c| acquired(c, t) >= n),
    })
}

#[no_mangle]
pub extern "C" fn DAQmxWaitUntilTaskDone(task_handle: TaskHandle, time_to_wait: float64) -> int32 {
    guard(-1, || {
        let deadline = if time_to_wait < 0.0 {
            f64::INFINITY
        } else {
            now() + time_to_wait
        };
        loop {
            let r = with_bench(|b| {
                let t = now();
                sync(b, t);
                let name = task_name(b, task_handle);
                match done(b, task_handle, t) {
                    Err(e) => Some(finish(
                        b,
                        format!(
                            "DAQmxWaitUntilTaskDone({})",
                            name.clone().unwrap_or_default()
                        ),
                        name.as_deref(),
                        Err(e),
                    )),
                    Ok(true) => Some(finish(
                        b,
                        format!(
                            "DAQmxWaitUntilTaskDone({}, timeToWait={time_to_wait})",
                            name.clone().unwrap_or_default()
                        ),
                        name.as_deref(),
                        Ok(()),
                    )),
                    Ok(false) if t >= deadline => Some(finish(
                        b,
                        format!(
                            "DAQmxWaitUntilTaskDone({}, timeToWait={time_to_wait})",
                            name.clone().unwrap_or_default()
                        ),
                        name.as_deref(),
                        fail(WAIT_UNTIL_DONE_NOT_DONE, ""),
                    )),
                    Ok(false) => None,
                }
            });
            if let Some(code) = r {
                return code;
            }
            sleep_until((now() + 0.001).min(deadline));
        }
    })
}

// ---------------------------------------------------------------- exports: channels, timing

/// # Safety
/// The strings are NULL or C strings.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn DAQmxCreateAIVoltageChan(
    task_handle: TaskHandle,
    physical_channel: *const c_char,
    name_to_assign_to_channel: *const c_char,
    terminal_config: int32,
    min_val: float64,
    max_val: float64,
    units: int32,
    custom_scale_name: *const c_char,
) -> int32 {
    guard(-1, || {
        let phys = cstr(physical_channel);
        let name = cstr(name_to_assign_to_channel);
        let _ = cstr(custom_scale_name);
        with_bench(|b| {
            let tn = task_name(b, task_handle);
            let r = add_chans(
                b,
                task_handle,
                &phys,
                &name,
                Kind::Ai,
                terminal_config,
                min_val,
                max_val,
                units,
            );
            finish(
                b,
                format!("DAQmxCreateAIVoltageChan({}, physicalChannel=\"{phys}\", terminalConfig={terminal_config}, minVal={min_val}, maxVal={max_val}, units={units})", tn.clone().unwrap_or_default()),
                tn.as_deref(),
                r,
            )
        })
    })
}

/// # Safety
/// The strings are NULL or C strings.
#[no_mangle]
pub unsafe extern "C" fn DAQmxCreateAOVoltageChan(
    task_handle: TaskHandle,
    physical_channel: *const c_char,
    name_to_assign_to_channel: *const c_char,
    min_val: float64,
    max_val: float64,
    units: int32,
    custom_scale_name: *const c_char,
) -> int32 {
    guard(-1, || {
        let phys = cstr(physical_channel);
        let name = cstr(name_to_assign_to_channel);
        let _ = cstr(custom_scale_name);
        with_bench(|b| {
            let tn = task_name(b, task_handle);
            let r = add_chans(
                b,
                task_handle,
                &phys,
                &name,
                Kind::Ao,
                VAL_CFG_DEFAULT,
                min_val,
                max_val,
                units,
            );
            finish(
                b,
                format!("DAQmxCreateAOVoltageChan({}, physicalChannel=\"{phys}\", minVal={min_val}, maxVal={max_val}, units={units})", tn.clone().unwrap_or_default()),
                tn.as_deref(),
                r,
            )
        })
    })
}

/// A terminal name relative to the device: `ao/SampleClock` for `/Dev1/ao/SampleClock`.
fn terminal(b: &Bench, s: &str) -> R<String> {
    let s = s.trim();
    if let Some(rest) = s.strip_prefix('/') {
        let (dev, term) = rest.split_once('/').unwrap_or((rest, ""));
        device_ok(b, dev)?;
        Ok(term.to_ascii_lowercase())
    } else {
        Ok(s.to_ascii_lowercase())
    }
}

fn is_pfi(term: &str) -> bool {
    term.strip_prefix("pfi")
        .and_then(|n| n.parse::<u32>().ok())
        .is_some_and(|n| n <= 9)
}

/// # Safety
/// `source` is NULL or a C string.
#[no_mangle]
pub unsafe extern "C" fn DAQmxCfgSampClkTiming(
    task_handle: TaskHandle,
    source: *const c_char,
    rate: float64,
    active_edge: int32,
    sample_mode: int32,
    samps_per_chan: uInt64,
) -> int32 {
    guard(-1, || {
        let src = cstr(source);
        with_bench(|b| {
            let tn = task_name(b, task_handle);
            let r = (|| {
                let kind = task_mut(b, task_handle)?.kind;
                let term = terminal(b, &src)?;
                let clock = match term.as_str() {
                    "" | "onboardclock" => Clock::Onboard,
                    "ao/sampleclock" if kind == Some(Kind::Ai) => Clock::AoSampleClock,
                    t if is_pfi(t) => Clock::External,
                    _ => {
                        return fail(
                            ROUTE_SRC_NOT_FOUND,
                            format!("Property: DAQmx_SampClk_Src\nProperty: DAQmx_SampClk_ActiveEdge\nSource Device: {}\nSource Terminal: {src}", b.daq.device),
                        )
                    }
                };
                let max = if kind == Some(Kind::Ao) {
                    AO_MAX_RATE_1
                } else {
                    AI_MAX_RATE
                };
                if !(rate.is_finite() && rate > 0.0 && rate <= max) {
                    return fail(
                        INVALID_ATTRIBUTE_VALUE,
                        format!(
                            "Property: DAQmx_SampClk_Rate\nRequested Value: {}\nValid Values Begin with: {}\nValid Values End with: {}",
                            fmt_v(rate),
                            fmt_v(1e-3),
                            fmt_v(max)
                        ),
                    );
                }
                if active_edge != VAL_RISING && active_edge != VAL_FALLING {
                    return fail(
                        INVALID_ATTRIBUTE_VALUE,
                        format!("Property: DAQmx_SampClk_ActiveEdge\nRequested Value: {active_edge}\nYou Can Select: DAQmx_Val_Rising, DAQmx_Val_Falling"),
                    );
                }
                let finite = match sample_mode {
                    VAL_FINITE_SAMPS => {
                        if samps_per_chan < 2 {
                            return fail(
                                INVALID_ATTRIBUTE_VALUE,
                                format!("Property: DAQmx_SampQuant_SampPerChan\nRequested Value: {samps_per_chan}\nValid Values Begin with: 2\nValid Values End with: 18446744073709551615"),
                            );
                        }
                        Some(samps_per_chan)
                    }
                    VAL_CONT_SAMPS => None,
                    _ => {
                        return fail(
                            INVALID_ATTRIBUTE_VALUE,
                            format!("Property: DAQmx_SampQuant_SampMode\nRequested Value: {sample_mode}\nYou Can Select: DAQmx_Val_FiniteSamps, DAQmx_Val_ContSamps"),
                        )
                    }
                };
                let t = task_mut(b, task_handle)?;
                if t.running {
                    return fail(OP_WHILE_TASK_RUNNING, "");
                }
                t.timing = Some(Timing {
                    clock,
                    rate,
                    finite,
                    samps_per_chan,
                });
                Ok(())
            })();
            finish(
                b,
                format!("DAQmxCfgSampClkTiming({}, source=\"{src}\", rate={rate}, activeEdge={active_edge}, sampleMode={sample_mode}, sampsPerChan={samps_per_chan})", tn.clone().unwrap_or_default()),
                tn.as_deref(),
                r,
            )
        })
    })
}

/// # Safety
/// `trigger_source` is NULL or a C string.
#[no_mangle]
pub unsafe extern "C" fn DAQmxCfgDigEdgeStartTrig(
    task_handle: TaskHandle,
    trigger_source: *const c_char,
    trigger_edge: int32,
) -> int32 {
    guard(-1, || {
        let src = cstr(trigger_source);
        with_bench(|b| {
            let tn = task_name(b, task_handle);
            let r = (|| {
                let kind = task_mut(b, task_handle)?.kind;
                let term = terminal(b, &src)?;
                let trig = match term.as_str() {
                    "ao/starttrigger" if kind == Some(Kind::Ai) => Trigger::AoStart,
                    t if is_pfi(t) => Trigger::External,
                    _ => {
                        return fail(
                            ROUTE_SRC_NOT_FOUND,
                            format!("Property: DAQmx_DigEdge_StartTrig_Src\nSource Device: {}\nSource Terminal: {src}", b.daq.device),
                        )
                    }
                };
                if trigger_edge != VAL_RISING && trigger_edge != VAL_FALLING {
                    return fail(
                        INVALID_ATTRIBUTE_VALUE,
                        format!("Property: DAQmx_DigEdge_StartTrig_Edge\nRequested Value: {trigger_edge}\nYou Can Select: DAQmx_Val_Rising, DAQmx_Val_Falling"),
                    );
                }
                let t = task_mut(b, task_handle)?;
                if t.running {
                    return fail(OP_WHILE_TASK_RUNNING, "");
                }
                t.trigger = Some(trig);
                Ok(())
            })();
            finish(
                b,
                format!("DAQmxCfgDigEdgeStartTrig({}, triggerSource=\"{src}\", triggerEdge={trigger_edge})", tn.clone().unwrap_or_default()),
                tn.as_deref(),
                r,
            )
        })
    })
}

#[no_mangle]
pub extern "C" fn DAQmxDisableStartTrig(task_handle: TaskHandle) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let tn = task_name(b, task_handle);
            let r = task_mut(b, task_handle).map(|t| t.trigger = None);
            finish(
                b,
                format!("DAQmxDisableStartTrig({})", tn.clone().unwrap_or_default()),
                tn.as_deref(),
                r,
            )
        })
    })
}

#[no_mangle]
pub extern "C" fn DAQmxCfgInputBuffer(
    task_handle: TaskHandle,
    num_samps_per_chan: uInt32,
) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let tn = task_name(b, task_handle);
            let r =
                task_mut(b, task_handle).map(|t| t.input_buf = Some(u64::from(num_samps_per_chan)));
            finish(
                b,
                format!(
                    "DAQmxCfgInputBuffer({}, numSampsPerChan={num_samps_per_chan})",
                    tn.clone().unwrap_or_default()
                ),
                tn.as_deref(),
                r,
            )
        })
    })
}

#[no_mangle]
pub extern "C" fn DAQmxCfgOutputBuffer(
    task_handle: TaskHandle,
    num_samps_per_chan: uInt32,
) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let tn = task_name(b, task_handle);
            let r = task_mut(b, task_handle).map(|t| t.ao_cap = Some(num_samps_per_chan as u64));
            finish(
                b,
                format!(
                    "DAQmxCfgOutputBuffer({}, numSampsPerChan={num_samps_per_chan})",
                    tn.clone().unwrap_or_default()
                ),
                tn.as_deref(),
                r,
            )
        })
    })
}

#[no_mangle]
pub extern "C" fn DAQmxSetWriteRegenMode(task_handle: TaskHandle, data: int32) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let tn = task_name(b, task_handle);
            let r = task_mut(b, task_handle).and_then(|t| match data {
                VAL_ALLOW_REGEN => {
                    t.regen = true;
                    Ok(())
                }
                VAL_DO_NOT_ALLOW_REGEN => {
                    t.regen = false;
                    Ok(())
                }
                _ => fail(
                    INVALID_ATTRIBUTE_VALUE,
                    format!("Property: DAQmx_Write_RegenMode\nRequested Value: {data}\nYou Can Select: DAQmx_Val_AllowRegen, DAQmx_Val_DoNotAllowRegen"),
                ),
            });
            finish(
                b,
                format!(
                    "DAQmxSetWriteRegenMode({}, data={data})",
                    tn.clone().unwrap_or_default()
                ),
                tn.as_deref(),
                r,
            )
        })
    })
}

/// `int32 DAQmxSetReadWaitMode(TaskHandle taskHandle, int32 data)`.
#[no_mangle]
pub extern "C" fn DAQmxSetReadWaitMode(task_handle: TaskHandle, data: int32) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let tn = task_name(b, task_handle);
            let r = task_mut(b, task_handle).and_then(|t| match data {
                VAL_WAIT_FOR_INTERRUPT | VAL_POLL | VAL_YIELD | VAL_SLEEP => {
                    t.wait_mode = data;
                    Ok(())
                }
                _ => fail(
                    INVALID_ATTRIBUTE_VALUE,
                    format!("Property: DAQmx_Read_WaitMode\nRequested Value: {data}\nYou Can Select: DAQmx_Val_WaitForInterrupt, DAQmx_Val_Poll, DAQmx_Val_Yield, DAQmx_Val_Sleep"),
                ),
            });
            finish(
                b,
                format!(
                    "DAQmxSetReadWaitMode({}, data={data})",
                    tn.clone().unwrap_or_default()
                ),
                tn.as_deref(),
                r,
            )
        })
    })
}

/// # Safety
/// `data` points to a `float64`.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetSampClkRate(task_handle: TaskHandle, data: *mut float64) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let tn = task_name(b, task_handle);
            let r = task_mut(b, task_handle).and_then(|t| match (t.timing, data.is_null()) {
                (_, true) => fail(NULL_PTR, ""),
                (Some(tm), false) => {
                    *data = tm.rate;
                    Ok(())
                }
                (None, false) => fail(ATTRIBUTE_NOT_SUPPORTED, "Property: DAQmx_SampClk_Rate"),
            });
            finish(
                b,
                format!("DAQmxGetSampClkRate({})", tn.clone().unwrap_or_default()),
                tn.as_deref(),
                r,
            )
        })
    })
}

// ---------------------------------------------------------------- exports: read

/// # Safety
/// `read_array` points to `array_size_in_samps` doubles; `samps_per_chan_read` is NULL or
/// points to an `int32`.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn DAQmxReadAnalogF64(
    task_handle: TaskHandle,
    num_samps_per_chan: int32,
    timeout: float64,
    fill_mode: bool32,
    read_array: *mut float64,
    array_size_in_samps: uInt32,
    samps_per_chan_read: *mut int32,
    _reserved: *mut bool32,
) -> int32 {
    guard(-1, || {
        if !samps_per_chan_read.is_null() {
            *samps_per_chan_read = 0;
        }
        let (code, n) = read(
            task_handle,
            num_samps_per_chan,
            timeout,
            fill_mode,
            read_array,
            array_size_in_samps as usize,
        );
        if !samps_per_chan_read.is_null() {
            *samps_per_chan_read = n as i32;
        }
        code
    })
}

/// # Safety
/// `value` points to a `float64`.
#[no_mangle]
pub unsafe extern "C" fn DAQmxReadAnalogScalarF64(
    task_handle: TaskHandle,
    timeout: float64,
    value: *mut float64,
    _reserved: *mut bool32,
) -> int32 {
    guard(-1, || {
        if value.is_null() {
            return with_bench(|b| {
                finish(
                    b,
                    "DAQmxReadAnalogScalarF64()".into(),
                    None,
                    fail(NULL_PTR, ""),
                )
            });
        }
        let mut one = [0.0f64; 8];
        let (code, _) = read(
            task_handle,
            1,
            timeout,
            VAL_GROUP_BY_SCAN_NUMBER,
            one.as_mut_ptr(),
            8,
        );
        if code == 0 {
            *value = one[0];
        }
        code
    })
}

enum Step {
    Done(i32, u64),
    Wait(f64),
}

/// The read: returns the status code and the samples per channel read.
unsafe fn read(
    h: TaskHandle,
    num: i32,
    timeout: f64,
    fill: u32,
    out: *mut f64,
    size: usize,
) -> (i32, u64) {
    let t_call = now();
    let deadline = if timeout < 0.0 {
        f64::INFINITY
    } else {
        t_call + timeout
    };
    let mut first = true;
    loop {
        let (step, poll) = with_bench(|b| {
            let poll = b
                .daq
                .tasks
                .get(&id_of(h))
                .is_some_and(|t| t.wait_mode == VAL_POLL);
            (
                read_step(b, h, num, deadline, fill, out, size, &mut first),
                poll,
            )
        });
        match step {
            Step::Done(code, n) => return (code, n),
            Step::Wait(until) => {
                let until = until.min(deadline).min(now() + 0.005);
                if poll {
                    while now() < until {
                        std::hint::spin_loop();
                    }
                } else {
                    sleep_until(until)
                }
            }
        }
    }
}

#[allow(clippy::too_many_arguments)]
unsafe fn read_step(
    b: &mut Bench,
    h: TaskHandle,
    num: i32,
    deadline: f64,
    fill: u32,
    out: *mut f64,
    size: usize,
    first: &mut bool,
) -> Step {
    let t = now();
    sync(b, t);
    let tn = task_name(b, h);
    let call = format!(
        "DAQmxReadAnalogF64({}, numSampsPerChan={num})",
        tn.clone().unwrap_or_default()
    );
    let is_first = std::mem::replace(first, false);
    macro_rules! bail {
        ($code:expr, $detail:expr) => {
            return Step::Done(finish(b, call, tn.as_deref(), fail($code, $detail)), 0)
        };
    }
    let task = match task_mut(b, h) {
        Ok(t) => t.clone(),
        Err(Fail(c, d)) => bail!(c, d),
    };
    if is_first {
        // the fault switches count the read calls
        b.daq.reads += 1;
        if let Some(n) = b.cfg.faults.daq_removed_after_reads {
            if b.daq.reads > n {
                b.daq.removed = true;
            }
        }
    }
    if b.daq.removed {
        let dev = b.daq.device.clone();
        bail!(DEV_CANNOT_BE_ACCESSED, format!("Device: {dev}"));
    }
    match task.kind {
        None => bail!(NO_CHANS_IN_TASK, ""),
        Some(Kind::Ao) => bail!(READ_CHAN_TYPE_MISMATCH, ""),
        Some(Kind::Ai) => {}
    }
    if fill != VAL_GROUP_BY_CHANNEL && fill != VAL_GROUP_BY_SCAN_NUMBER {
        bail!(
            INVALID_ATTRIBUTE_VALUE,
            format!("Property: fillMode\nRequested Value: {fill}")
        );
    }
    if out.is_null() {
        bail!(NULL_PTR, "");
    }
    let id = id_of(h);
    if task.timing.is_none() {
        // on demand: one sample per channel now
        if is_first && !task.running {
            if let Err(Fail(c, d)) = start_task(b, id, true) {
                bail!(c, d);
            }
            b.daq.tasks.get_mut(&id).expect("exists").running = false;
        }
        let nch = task.chans.len();
        if size < nch {
            bail!(
                READ_BUFFER_TOO_SMALL,
                format!("Buffer Size: {size}\nRequired: {nch}")
            );
        }
        let clock = (t, 1.0, None, f64::INFINITY);
        let dst = std::slice::from_raw_parts_mut(out, nch);
        produce(b, id, clock, 0, 1, fill == VAL_GROUP_BY_SCAN_NUMBER, dst);
        b.log(format!("{call} -> 0 [1 sample per channel, on demand]"));
        return Step::Done(0, 1);
    }
    if !task.running {
        if !is_first {
            bail!(INVALID_TASK, "the task was stopped during the read");
        }
        // DAQmx starts a task that was not started (the read's implicit start)
        if let Err(Fail(c, d)) = start_task(b, id, true) {
            bail!(c, d);
        }
    }
    let task = b.daq.tasks[&id].clone();
    let timing = task.timing.expect("timed");
    if is_first {
        if let Some(n) = b.cfg.faults.overflow_after_reads {
            if timing.finite.is_none() && b.daq.reads > n {
                b.daq.tasks.get_mut(&id).expect("exists").overflowed = true;
            }
        }
    }
    if b.daq.tasks[&id].overflowed {
        bail!(SAMPLES_NO_LONGER_AVAILABLE, "Property: DAQmx_Read_RelativeTo\nCorresponding Value: DAQmx_Val_CurrReadPos\nProperty: DAQmx_Read_Offset\nCorresponding Value: 0");
    }
    let clock = ai_clock(b, &task);
    let have = clock.map_or(0, |c| acquired(c, t));
    let unread = have.saturating_sub(task.read_pos);
    if timing.finite.is_none() && unread > task.buffer_size() {
        b.daq.tasks.get_mut(&id).expect("exists").overflowed = true;
        bail!(SAMPLES_NO_LONGER_AVAILABLE, format!("Property: DAQmx_Read_RelativeTo\nCorresponding Value: DAQmx_Val_CurrReadPos\nProperty: DAQmx_Read_Offset\nCorresponding Value: 0\nBuffer Size: {} samples per channel\nUnread: {unread}", task.buffer_size()));
    }
    let want: u64 = if num == VAL_AUTO {
        match timing.finite {
            Some(n) => n.saturating_sub(task.read_pos),
            None => unread,
        }
    } else if num < 0 {
        bail!(
            INVALID_ATTRIBUTE_VALUE,
            format!(
                "Property: numSampsPerChan\nRequested Value: {num}\nValid Values Begin with: -1"
            )
        );
    } else {
        num as u64
    };
    if let Some(n) = timing.finite {
        if task.read_pos + want > n {
            bail!(SAMPLES_WILL_NEVER_BE_AVAILABLE, format!("Attempted to Read Sample: {}\nProperty: DAQmx_Read_RelativeTo\nCorresponding Value: DAQmx_Val_CurrReadPos", task.read_pos + want - 1));
        }
    }
    let nch = task.chans.len();
    if (want as usize).saturating_mul(nch) > size {
        bail!(
            READ_BUFFER_TOO_SMALL,
            format!(
                "Buffer Size: {size}\nRequired Buffer Size: {}",
                want as usize * nch
            )
        );
    }
    if unread >= want {
        let clock = clock.expect("samples exist");
        let mut buf = vec![0.0; want as usize * nch];
        produce(
            b,
            id,
            clock,
            task.read_pos,
            want,
            fill == VAL_GROUP_BY_SCAN_NUMBER,
            &mut buf,
        );
        std::ptr::copy_nonoverlapping(buf.as_ptr(), out, buf.len());
        b.daq.tasks.get_mut(&id).expect("exists").read_pos += want;
        b.log(format!("{call} -> 0 [{want} samples per channel]"));
        return Step::Done(0, want);
    }
    if t >= deadline {
        // the samples read before the timeout, then −200284
        let got = unread;
        if got > 0 {
            let clock = clock.expect("samples exist");
            let mut buf = vec![0.0; got as usize * nch];
            produce(
                b,
                id,
                clock,
                task.read_pos,
                got,
                fill == VAL_GROUP_BY_SCAN_NUMBER,
                &mut buf,
            );
            // GroupByChannel with fewer samples: channel blocks of `got` each
            std::ptr::copy_nonoverlapping(buf.as_ptr(), out, buf.len());
            b.daq.tasks.get_mut(&id).expect("exists").read_pos += got;
        }
        let code = finish(
            b,
            call,
            tn.as_deref(),
            fail(SAMPLES_NOT_YET_AVAILABLE, format!("Property: DAQmx_Read_RelativeTo\nCorresponding Value: DAQmx_Val_CurrReadPos\nProperty: DAQmx_Read_Offset\nCorresponding Value: 0\nSamples Requested: {want}\nSamples Available: {got}")),
        );
        return Step::Done(code, got);
    }
    // wait for the last wanted sample's time
    let until = match clock {
        Some((t0, dt, _, _)) => t0 + (task.read_pos + want - 1) as f64 * dt + 1e-7,
        None => t + 0.002,
    };
    Step::Wait(until)
}

// ---------------------------------------------------------------- exports: write

fn write(
    b: &mut Bench,
    h: TaskHandle,
    n: i32,
    auto_start: bool,
    by_scan: bool,
    data: &[f64],
) -> R<i32> {
    let t = now();
    sync(b, t);
    // the task's settings (not its sample buffer: a stream's holds up to its whole block)
    let task = {
        let tk = task_mut(b, h)?;
        let buf = std::mem::take(&mut tk.ao_buf);
        let copy = tk.clone();
        tk.ao_buf = buf;
        copy
    };
    if b.daq.removed {
        let dev = b.daq.device.clone();
        return fail(DEV_CANNOT_BE_ACCESSED, format!("Device: {dev}"));
    }
    match task.kind {
        None => return fail(NO_CHANS_IN_TASK, ""),
        Some(Kind::Ai) => return fail(WRITE_CHAN_TYPE_MISMATCH, ""),
        Some(Kind::Ao) => {}
    }
    if task.underflow {
        return fail(GEN_STOPPED_TO_PREVENT_REGEN_OF_OLD_SAMPLES, "");
    }
    if n < 0 {
        return fail(
            NEGATIVE_WRITE_SAMPLE_NUMBER,
            format!("Samples Per Channel: {n}"),
        );
    }
    if n == 0 {
        return Ok(0);
    }
    let n = n as usize;
    let nch = task.chans.len();
    // per channel
    let mut per: Vec<Vec<f64>> = vec![Vec::with_capacity(n); nch];
    for k in 0..n {
        for (c, p) in per.iter_mut().enumerate() {
            let v = if by_scan {
                data[k * nch + c]
            } else {
                data[c * n + k]
            };
            p.push(v);
        }
    }
    for (c, p) in per.iter().enumerate() {
        let ch = &task.chans[c];
        if let Some(v) = p
            .iter()
            .find(|v| !(v.is_finite() && (ch.min..=ch.max).contains(*v)))
        {
            return fail(
                INVALID_AO_DATA_WRITE,
                format!(
                    "Channel Name: {}\nValue Requested: {}\nMinimum: {}\nMaximum: {}",
                    ch.name,
                    fmt_v(*v),
                    fmt_v(ch.min),
                    fmt_v(ch.max)
                ),
            );
        }
    }
    let id = id_of(h);
    match task.timing {
        None => {
            let last: Vec<f64> = per.iter().map(|p| *p.last().expect("n ≥ 1")).collect();
            if task.running || auto_start {
                let phys: Vec<usize> = task.chans.iter().map(|c| c.phys).collect();
                for (p, v) in phys.into_iter().zip(last) {
                    set_ao(b, p, t, v);
                }
                if !task.running {
                    // DAQmx's autoStart of an on-demand task: started and stopped around the write
                    b.daq.tasks.get_mut(&id).expect("exists").running = false;
                }
            } else {
                b.daq.tasks.get_mut(&id).expect("exists").ao_pending = Some(last);
            }
        }
        Some(_) => {
            let tk = b.daq.tasks.get_mut(&id).expect("exists");
            if tk.running && tk.regen {
                // a new buffer while regenerating: played from the next sample on
                tk.ao_buf = per;
            } else if tk.running {
                for (buf, p) in tk.ao_buf.iter_mut().zip(per) {
                    buf.extend(p);
                }
            } else {
                tk.ao_buf = per;
                if tk.ao_cap.is_none_or(|c| c < n as u64) {
                    tk.ao_cap = Some(n as u64);
                }
            }
            if auto_start && !tk.running {
                start_task(b, id, false)?;
            }
        }
    }
    Ok(n as i32)
}

/// # Safety
/// `write_array` points to `num_samps_per_chan` × channels doubles; `samps_per_chan_written`
/// is NULL or points to an `int32`.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn DAQmxWriteAnalogF64(
    task_handle: TaskHandle,
    num_samps_per_chan: int32,
    auto_start: bool32,
    timeout: float64,
    data_layout: bool32,
    write_array: *const float64,
    samps_per_chan_written: *mut int32,
    _reserved: *mut bool32,
) -> int32 {
    guard(-1, || {
        // a stream's buffer full: wait (outside the bench's lock) for the space, up to the
        // timeout
        let t_call = now();
        let deadline = if timeout < 0.0 {
            f64::INFINITY
        } else {
            t_call + timeout
        };
        let mut timed_out = false;
        let mut waited = false;
        loop {
            let wait = with_bench(|b| {
                let t = now();
                sync(b, t);
                space_wait(b, task_handle, num_samps_per_chan.max(0) as u64)
            });
            match wait {
                None => break,
                Some(_) if now() >= deadline => {
                    timed_out = true;
                    break;
                }
                Some(until) => {
                    waited = true;
                    sleep_until(until.min(deadline).min(now() + 0.005))
                }
            }
        }
        with_bench(|b| {
            let tn = task_name(b, task_handle);
            let nch = b
                .daq
                .tasks
                .get(&id_of(task_handle))
                .map_or(0, |t| t.chans.len());
            let r = (|| {
                if timed_out {
                    let free = space_avail(b, task_handle).unwrap_or(0);
                    return fail(
                        SAMPLES_CAN_NOT_YET_BE_WRITTEN,
                        format!("Space Available in Buffer: {free}\nSamples Requested: {num_samps_per_chan}\nWaited: {:.6} s", now() - t_call),
                    );
                }
                if write_array.is_null() {
                    return fail(NULL_PTR, "");
                }
                if data_layout != VAL_GROUP_BY_CHANNEL && data_layout != VAL_GROUP_BY_SCAN_NUMBER {
                    return fail(
                        INVALID_ATTRIBUTE_VALUE,
                        format!("Property: dataLayout\nRequested Value: {data_layout}"),
                    );
                }
                let len = (num_samps_per_chan.max(0) as usize) * nch;
                let data = std::slice::from_raw_parts(write_array, len);
                write(
                    b,
                    task_handle,
                    num_samps_per_chan,
                    auto_start != 0,
                    data_layout == VAL_GROUP_BY_SCAN_NUMBER,
                    data,
                )
            })();
            if !samps_per_chan_written.is_null() {
                *samps_per_chan_written = *r.as_ref().unwrap_or(&0);
            }
            let first: Vec<String> = if write_array.is_null() || nch == 0 || num_samps_per_chan < 1
            {
                Vec::new()
            } else {
                std::slice::from_raw_parts(write_array, nch.min(num_samps_per_chan as usize * nch))
                    .iter()
                    .map(|v| v.to_string())
                    .collect()
            };
            finish(
                b,
                format!(
                    "DAQmxWriteAnalogF64({}, numSampsPerChan={num_samps_per_chan}, autoStart={auto_start}, timeout={timeout}, dataLayout={data_layout}, first=[{}]){}",
                    tn.clone().unwrap_or_default(),
                    first.join(", "),
                    if waited { format!(" waited {:.6} s for room", now() - t_call) } else { String::new() }
                ),
                tn.as_deref(),
                r.map(|_| ()),
            )
        })
    })
}

/// The samples per channel a write can put in task `h`'s buffer now: the buffer's size less
/// what was written and not yet played (a running stream), or less what is buffered (before
/// the start). `None`: not a timed AO task.
fn space_avail(b: &Bench, h: TaskHandle) -> Option<u64> {
    let t = b.daq.tasks.get(&id_of(h))?;
    if t.kind != Some(Kind::Ao) || t.timing.is_none() {
        return None;
    }
    let buffered = t.ao_buf.first().map_or(0, Vec::len) as u64;
    let cap = t.ao_cap.unwrap_or(0);
    let stream = !t.regen && t.timing.is_some_and(|tm| tm.finite.is_none());
    let pending = if t.running && stream {
        (t.ao_base + buffered).saturating_sub(t.ao_next)
    } else {
        buffered
    };
    Some(cap.saturating_sub(pending))
}

/// When a write of `n` samples per channel to a running stream (regeneration off) must wait
/// for space: the bench time at which the generation will have played enough. `None`: it
/// need not wait (not a running stream, room enough, or the generation has stopped).
fn space_wait(b: &Bench, h: TaskHandle, n: u64) -> Option<f64> {
    let t = b.daq.tasks.get(&id_of(h))?;
    let stream = t.kind == Some(Kind::Ao)
        && !t.regen
        && t.running
        && !t.underflow
        && t.timing.is_some_and(|tm| tm.finite.is_none());
    if !stream {
        return None;
    }
    let free = space_avail(b, h)?;
    if free >= n || n > t.ao_cap.unwrap_or(0) {
        // a block larger than the whole buffer never fits: not waited for here (NI's
        // driver splits it; the bench's writes never are)
        return None;
    }
    let clk = b.daq.ao_clock?;
    let edge = t.ao_next + (n - free);
    let at = clk.t0 + edge as f64 * clk.dt;
    (at < clk.end).then_some(at)
}

/// `int32 DAQmxGetWriteSpaceAvail(TaskHandle taskHandle, uInt32 *data)`: the samples per
/// channel a write can put in the buffer now.
///
/// # Safety
/// `data` is NULL or points to a `uInt32`.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetWriteSpaceAvail(
    task_handle: TaskHandle,
    data: *mut uInt32,
) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let t = now();
            sync(b, t);
            let tn = task_name(b, task_handle);
            let r = (|| {
                task_mut(b, task_handle)?;
                if data.is_null() {
                    return fail(NULL_PTR, "");
                }
                match space_avail(b, task_handle) {
                    Some(v) => {
                        *data = v.min(u32::MAX as u64) as u32;
                        Ok(v)
                    }
                    None => fail(ATTRIBUTE_NOT_SUPPORTED, "Property: DAQmx_Write_SpaceAvail"),
                }
            })();
            let v = r.as_ref().map_or(String::new(), |v| format!(" = {v}"));
            finish(
                b,
                format!(
                    "DAQmxGetWriteSpaceAvail({}){v}",
                    tn.clone().unwrap_or_default()
                ),
                tn.as_deref(),
                r.map(|_| ()),
            )
        })
    })
}

#[no_mangle]
pub extern "C" fn DAQmxWriteAnalogScalarF64(
    task_handle: TaskHandle,
    auto_start: bool32,
    timeout: float64,
    value: float64,
    _reserved: *mut bool32,
) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let tn = task_name(b, task_handle);
            let r = (|| {
                let t = task_mut(b, task_handle)?;
                if t.chans.len() > 1 {
                    return fail(WRITE_NUM_CHANS_MISMATCH, "");
                }
                if t.timing.is_some() {
                    return fail(INVALID_ATTRIBUTE_VALUE, "Property: DAQmx_SampTimingType\nRequested Value: DAQmx_Val_SampClk\nYou Can Select: DAQmx_Val_OnDemand");
                }
                write(b, task_handle, 1, auto_start != 0, false, &[value]).map(|_| ())
            })();
            finish(
                b,
                format!("DAQmxWriteAnalogScalarF64({}, autoStart={auto_start}, timeout={timeout}, value={value})", tn.clone().unwrap_or_default()),
                tn.as_deref(),
                r,
            )
        })
    })
}

// ---------------------------------------------------------------- exports: errors, device

/// # Safety
/// `error_string` is NULL or points to `buffer_size` bytes.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetErrorString(
    error_code: int32,
    error_string: *mut c_char,
    buffer_size: uInt32,
) -> int32 {
    guard(-1, || {
        let text = daqmx_text(error_code);
        let need = put_cstr(text, error_string, buffer_size as usize);
        if buffer_size == 0 || error_string.is_null() {
            need as i32
        } else {
            0
        }
    })
}

/// # Safety
/// `error_string` is NULL or points to `buffer_size` bytes.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetExtendedErrorInfo(
    error_string: *mut c_char,
    buffer_size: uInt32,
) -> int32 {
    guard(-1, || {
        let text = with_bench(|b| {
            b.daq
                .last_error
                .as_ref()
                .map(|e| e.1.clone())
                .unwrap_or_default()
        });
        let need = put_cstr(&text, error_string, buffer_size as usize);
        if buffer_size == 0 || error_string.is_null() {
            need as i32
        } else {
            0
        }
    })
}

/// # Safety
/// `device_name` is NULL or a C string.
#[no_mangle]
pub unsafe extern "C" fn DAQmxResetDevice(device_name: *const c_char) -> int32 {
    guard(-1, || {
        let dev = cstr(device_name);
        with_bench(|b| {
            let r = device_ok(b, &dev).map(|_| {
                let t = now();
                sync(b, t);
                let ids: Vec<usize> = b.daq.tasks.keys().copied().collect();
                for id in ids {
                    stop_task(b, id);
                }
                // the device's tasks are invalidated by the reset
                b.daq.tasks.clear();
                b.daq.ao_clock = None;
                b.daq.ao_start = None;
                for ch in 0..AO_CHANNELS {
                    set_ao(b, ch, t, 0.0);
                }
            });
            finish(b, format!("DAQmxResetDevice(\"{dev}\")"), None, r)
        })
    })
}

unsafe fn dev_string(
    name: &str,
    device: *const c_char,
    out: *mut c_char,
    size: uInt32,
    f: impl FnOnce(&Bench) -> String,
) -> int32 {
    let dev = cstr(device);
    with_bench(|b| {
        let r = device_ok(b, &dev);
        let code = finish(b, format!("{name}(\"{dev}\")"), None, r);
        if code != 0 {
            return code;
        }
        let s = f(b);
        let need = put_cstr(&s, out, size as usize);
        if size == 0 || out.is_null() {
            need as i32
        } else {
            0
        }
    })
}

unsafe fn dev_value<T: Copy>(name: &str, device: *const c_char, out: *mut T, v: T) -> int32 {
    let dev = cstr(device);
    with_bench(|b| {
        let r = device_ok(b, &dev).and_then(|_| {
            if out.is_null() {
                fail(NULL_PTR, "")
            } else {
                Ok(())
            }
        });
        let code = finish(b, format!("{name}(\"{dev}\")"), None, r);
        if code == 0 {
            *out = v;
        }
        code
    })
}

unsafe fn dev_array(
    name: &str,
    device: *const c_char,
    out: *mut f64,
    size: uInt32,
    v: &[f64],
) -> int32 {
    let dev = cstr(device);
    with_bench(|b| {
        let r = device_ok(b, &dev);
        let code = finish(b, format!("{name}(\"{dev}\")"), None, r);
        if code != 0 {
            return code;
        }
        if size == 0 || out.is_null() {
            return v.len() as i32;
        }
        let n = v.len().min(size as usize);
        std::ptr::copy_nonoverlapping(v.as_ptr(), out, n);
        0
    })
}

/// # Safety
/// `device` is a C string; `data` is NULL or points to `buffer_size` bytes.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetDevProductType(
    device: *const c_char,
    data: *mut c_char,
    buffer_size: uInt32,
) -> int32 {
    guard(-1, || {
        dev_string("DAQmxGetDevProductType", device, data, buffer_size, |_| {
            PRODUCT_TYPE.into()
        })
    })
}

/// # Safety
/// `device` is a C string; `data` points to a `uInt32`.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetDevSerialNum(device: *const c_char, data: *mut uInt32) -> int32 {
    guard(-1, || {
        let serial = with_bench(|b| b.daq.serial);
        dev_value("DAQmxGetDevSerialNum", device, data, serial)
    })
}

/// # Safety
/// `data` is NULL or points to `buffer_size` bytes.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetSysDevNames(data: *mut c_char, buffer_size: uInt32) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let names = if b.cfg.faults.daq_missing || b.daq.removed {
                String::new()
            } else {
                b.daq.device.clone()
            };
            b.log(format!("DAQmxGetSysDevNames() -> \"{names}\""));
            let need = put_cstr(&names, data, buffer_size as usize);
            if buffer_size == 0 || data.is_null() {
                need as i32
            } else {
                0
            }
        })
    })
}

/// # Safety
/// `device` is a C string; `data` points to a `float64`.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetDevAIMaxSingleChanRate(
    device: *const c_char,
    data: *mut float64,
) -> int32 {
    guard(-1, || {
        dev_value("DAQmxGetDevAIMaxSingleChanRate", device, data, AI_MAX_RATE)
    })
}

/// # Safety
/// `device` is a C string; `data` points to a `float64`.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetDevAIMaxMultiChanRate(
    device: *const c_char,
    data: *mut float64,
) -> int32 {
    guard(-1, || {
        dev_value("DAQmxGetDevAIMaxMultiChanRate", device, data, AI_MAX_RATE)
    })
}

/// # Safety
/// `device` is a C string; `data` points to a `float64`.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetDevAOMaxRate(device: *const c_char, data: *mut float64) -> int32 {
    guard(-1, || {
        dev_value("DAQmxGetDevAOMaxRate", device, data, AO_MAX_RATE_1)
    })
}

/// # Safety
/// `device` is a C string; `data` points to a `bool32`.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetDevAISimultaneousSamplingSupported(
    device: *const c_char,
    data: *mut bool32,
) -> int32 {
    guard(-1, || {
        dev_value(
            "DAQmxGetDevAISimultaneousSamplingSupported",
            device,
            data,
            1,
        )
    })
}

/// # Safety
/// `device` is a C string; `data` points to a `bool32`.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetDevIsSimulated(device: *const c_char, data: *mut bool32) -> int32 {
    guard(-1, || dev_value("DAQmxGetDevIsSimulated", device, data, 0))
}

/// # Safety
/// `device` is a C string; `data` is NULL or points to `array_size_in_elements` doubles.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetDevAIVoltageRngs(
    device: *const c_char,
    data: *mut float64,
    array_size_in_elements: uInt32,
) -> int32 {
    guard(-1, || {
        let v: Vec<f64> = AI_RANGES.iter().flat_map(|&r| [-r, r]).collect();
        dev_array(
            "DAQmxGetDevAIVoltageRngs",
            device,
            data,
            array_size_in_elements,
            &v,
        )
    })
}

/// # Safety
/// `device` is a C string; `data` is NULL or points to `array_size_in_elements` doubles.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetDevAOVoltageRngs(
    device: *const c_char,
    data: *mut float64,
    array_size_in_elements: uInt32,
) -> int32 {
    guard(-1, || {
        dev_array(
            "DAQmxGetDevAOVoltageRngs",
            device,
            data,
            array_size_in_elements,
            &[-AO_RANGE, AO_RANGE],
        )
    })
}

/// # Safety
/// `device` is a C string; `data` is NULL or points to `buffer_size` bytes.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetDevAIPhysicalChans(
    device: *const c_char,
    data: *mut c_char,
    buffer_size: uInt32,
) -> int32 {
    guard(-1, || {
        dev_string(
            "DAQmxGetDevAIPhysicalChans",
            device,
            data,
            buffer_size,
            |b| {
                (0..AI_CHANNELS)
                    .map(|i| format!("{}/ai{i}", b.daq.device))
                    .collect::<Vec<_>>()
                    .join(", ")
            },
        )
    })
}

/// # Safety
/// `device` is a C string; `data` is NULL or points to `buffer_size` bytes.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetDevAOPhysicalChans(
    device: *const c_char,
    data: *mut c_char,
    buffer_size: uInt32,
) -> int32 {
    guard(-1, || {
        dev_string(
            "DAQmxGetDevAOPhysicalChans",
            device,
            data,
            buffer_size,
            |b| {
                (0..AO_CHANNELS)
                    .map(|i| format!("{}/ao{i}", b.daq.device))
                    .collect::<Vec<_>>()
                    .join(", ")
            },
        )
    })
}

/// # Safety
/// `data` points to a `uInt32`.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetReadAvailSampPerChan(
    task_handle: TaskHandle,
    data: *mut uInt32,
) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let t = now();
            sync(b, t);
            let tn = task_name(b, task_handle);
            let r = task_mut(b, task_handle)
                .map(|t| t.clone())
                .and_then(|task| {
                    if data.is_null() {
                        return fail(NULL_PTR, "");
                    }
                    let have = ai_clock(b, &task).map_or(0, |c| acquired(c, t));
                    let unread = have.saturating_sub(task.read_pos);
                    *data = unread.min(if task.timing.is_some() {
                        task.buffer_size()
                    } else {
                        0
                    }) as u32;
                    Ok(())
                });
            finish(
                b,
                format!(
                    "DAQmxGetReadAvailSampPerChan({})",
                    tn.clone().unwrap_or_default()
                ),
                tn.as_deref(),
                r,
            )
        })
    })
}

/// # Safety
/// `data` points to a `uInt64`.
#[no_mangle]
pub unsafe extern "C" fn DAQmxGetReadTotalSampPerChanAcquired(
    task_handle: TaskHandle,
    data: *mut uInt64,
) -> int32 {
    guard(-1, || {
        with_bench(|b| {
            let t = now();
            sync(b, t);
            let tn = task_name(b, task_handle);
            let r = task_mut(b, task_handle)
                .map(|t| t.clone())
                .and_then(|task| {
                    if data.is_null() {
                        return fail(NULL_PTR, "");
                    }
                    *data = ai_clock(b, &task).map_or(0, |c| acquired(c, t));
                    Ok(())
                });
            finish(
                b,
                format!(
                    "DAQmxGetReadTotalSampPerChanAcquired({})",
                    tn.clone().unwrap_or_default()
                ),
                tn.as_deref(),
                r,
            )
        })
    })
}
