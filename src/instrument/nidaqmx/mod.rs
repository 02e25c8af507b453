//! An NI DAQ board (the paper's PCI-6120: 4 simultaneously sampled differential inputs, 800 kS/s
//! per channel, 16 bit, 2 analog outputs) as the QPD digitiser, through NI-DAQmx's C API
//! loaded at run time (`ffi.rs`, declared from `NIDAQmx.h`).
//!
//! **Point read.** One AI task per connection, created at connect (`DAQmxCreateTask`,
//! `DAQmxCreateAIVoltageChan` per input, ±`range_v`, the configured terminal configuration) and
//! reused: a read of n samples per channel is a finite acquisition on the board's clock
//! (`DAQmxCfgSampClkTiming` with `DAQmx_Val_FiniteSamps`, sent again only when n changes),
//! `DAQmxStartTask`, `DAQmxReadAnalogF64` with a timeout of n / rate plus `timeout_ms`, and
//! `DAQmxStopTask`. The means and spreads of Sx, Sy and the sum go through the same
//! `Calibration` as the other QPD backends.
//!
//! **Inputs.** Either the QPD amplifier's difference and sum outputs (`sx`, `sy`, `sum`) or
//! the four quadrants (`q1`…`q4`, numbered counter-clockwise from the top right as seen by the
//! detector): then Sx = (q1 + q4) − (q2 + q3), Sy = (q1 + q2) − (q3 + q4) and the sum is
//! q1 + q2 + q3 + q4, per sample, in volts, before the calibration.
//!
//! **Task hygiene.** Every task is stopped and cleared when its owner is dropped (exit,
//! reconnect, a fault: [`Task`]'s `Drop`), and a failed read stops the task before returning.
//!
//! **Errors.** Every negative return becomes an error naming the device, the function with its
//! arguments, the code with its `NIDAQmx.h` name and the text of `DAQmxGetExtendedErrorInfo`.
//! Positive returns are warnings and are not errors.

pub mod config;
pub use config::FAMILY;
pub mod ffi;
pub mod raster;
pub mod stream_stage;

use crate::instrument::scpi::Calibration;
use crate::instrument::{DeviceError, Qpd, QpdReading};
use ffi::{NiDaqmx, TaskHandle};
use std::ffi::CString;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

/// A DAQmx return code as a device error: device, call with arguments, code, its header
/// name and the library's extended error text (fetched now, on the failing thread).
pub fn daqmx_error(lib: &NiDaqmx, device: &str, call: &str, code: i32) -> DeviceError {
    let text = lib.extended_error_info();
    let text = if text.is_empty() {
        lib.error_string(code)
    } else {
        text
    };
    DeviceError::Controller {
        device: device.to_string(),
        command: call.to_string(),
        code: code as i64,
        message: format_daqmx_message(code, &text),
    }
}

/// `DAQmxErrorName: text` (the name when known, the library's text when it gave one).
pub fn format_daqmx_message(code: i32, text: &str) -> String {
    let name = ffi::error_name(code).unwrap_or("DAQmx error");
    let text = text.trim();
    if text.is_empty() {
        format!("{name} (no text from DAQmxGetExtendedErrorInfo)")
    } else {
        format!("{name}: {}", text.replace('\n', " "))
    }
}

/// Check a DAQmx return: negative is an error, 0 and positive (warnings) are not.
pub fn check(
    lib: &NiDaqmx,
    device: &str,
    call: impl FnOnce() -> String,
    r: i32,
) -> Result<(), DeviceError> {
    if r < 0 {
        Err(daqmx_error(lib, device, &call(), r))
    } else {
        Ok(())
    }
}

/// Terminal configuration of the analog inputs (`qpd.terminal`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Terminal {
    Default,
    Diff,
    Rse,
    Nrse,
    PseudoDiff,
}

impl Terminal {
    /// The config word: `"diff"`, `"rse"`, `"nrse"`, `"pseudodiff"`, `"default"`.
    pub fn parse(s: &str) -> Result<Terminal, String> {
        Ok(match s.trim().to_ascii_lowercase().as_str() {
            "diff" | "differential" => Terminal::Diff,
            "rse" => Terminal::Rse,
            "nrse" => Terminal::Nrse,
            "pseudodiff" => Terminal::PseudoDiff,
            "default" => Terminal::Default,
            _ => {
                return Err(format!(
                    "{s:?}: allowed are \"diff\" (the PCI-6120's only configuration), \"rse\", \"nrse\", \
                     \"pseudodiff\", \"default\""
                ))
            }
        })
    }

    /// The `DAQmx_Val_…` value of `DAQmxCreateAIVoltageChan`'s `terminalConfig`.
    pub fn daqmx(self) -> i32 {
        match self {
            Terminal::Default => ffi::DAQMX_VAL_CFG_DEFAULT,
            Terminal::Diff => ffi::DAQMX_VAL_DIFF,
            Terminal::Rse => ffi::DAQMX_VAL_RSE,
            Terminal::Nrse => ffi::DAQMX_VAL_NRSE,
            Terminal::PseudoDiff => ffi::DAQMX_VAL_PSEUDO_DIFF,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Terminal::Default => "DAQmx_Val_Cfg_Default",
            Terminal::Diff => "DAQmx_Val_Diff",
            Terminal::Rse => "DAQmx_Val_RSE",
            Terminal::Nrse => "DAQmx_Val_NRSE",
            Terminal::PseudoDiff => "DAQmx_Val_PseudoDiff",
        }
    }
}

/// A channel name as the config gives it (`"ai0"`, `"ao1"`): `kind` then a number 0–63. Also
/// accepted with the device in front (`"Dev1/ai0"`) when that device is `device`. Returns the
/// short name.
pub fn parse_channel(kind: &str, name: &str, device: &str) -> Result<String, String> {
    let n = name.trim();
    let short = match n.split_once('/') {
        Some((d, rest)) if d == device => rest,
        Some((d, _)) => {
            return Err(format!(
                "{name:?} names device {d:?}, but qpd.device is {device:?}: write just {:?}",
                n.rsplit('/').next().unwrap_or(n)
            ))
        }
        None => n,
    };
    let ok = short.strip_prefix(kind).and_then(|d| {
        d.parse::<u32>()
            .ok()
            .filter(|&k| k < 64 && d == k.to_string())
    });
    match ok {
        Some(_) => Ok(short.to_string()),
        None => Err(format!(
            "{name:?} is not an {} channel name: allowed are \"{kind}0\" … \"{kind}63\" (the PCI-6120 has \
             {kind}0–{kind}{})",
            if kind == "ai" { "analog input" } else { "analog output" },
            if kind == "ai" { 3 } else { 1 }
        )),
    }
}

/// The QPD signals and the inputs that carry them.
#[derive(Debug, Clone, PartialEq)]
pub enum NiInputs {
    /// The QPD amplifier's difference and sum outputs.
    Signals { sx: String, sy: String, sum: String },
    /// The four quadrants; Sx, Sy and the sum are formed per sample.
    Quadrants([String; 4]),
}

impl NiInputs {
    /// The input names in acquisition order.
    pub fn names(&self) -> Vec<String> {
        match self {
            NiInputs::Signals { sx, sy, sum } => vec![sx.clone(), sy.clone(), sum.clone()],
            NiInputs::Quadrants(q) => q.to_vec(),
        }
    }

    /// Sx, Sy, sum (V) of sample `i` of a `GroupByChannel` buffer of `n` samples per channel.
    pub fn signals(&self, buf: &[f64], n: usize, i: usize) -> [f64; 3] {
        match self {
            NiInputs::Signals { .. } => [buf[i], buf[n + i], buf[2 * n + i]],
            NiInputs::Quadrants(_) => {
                let q = |k: usize| buf[k * n + i];
                let (q1, q2, q3, q4) = (q(0), q(1), q(2), q(3));
                [
                    (q1 + q4) - (q2 + q3),
                    (q1 + q2) - (q3 + q4),
                    q1 + q2 + q3 + q4,
                ]
            }
        }
    }

    /// Which of Sx, Sy, sum of sample `i` come from an input at or beyond ±`range_v`: each
    /// signal's own input; with quadrant inputs a quadrant at the rail spoils all three.
    pub fn clipped(&self, buf: &[f64], n: usize, i: usize, range_v: f64) -> [bool; 3] {
        let rail = |k: usize| crate::instrument::range::at_rail(buf[k * n + i], range_v);
        match self {
            NiInputs::Signals { .. } => [rail(0), rail(1), rail(2)],
            NiInputs::Quadrants(_) => [(0..4).any(rail); 3],
        }
    }
}

/// Samples per signal (Sx, Sy, sum) of a `GroupByChannel` buffer of `n` samples per channel
/// whose inputs are at or beyond ±`range_v`.
pub fn clip_counts(inputs: &NiInputs, buf: &[f64], n: usize, range_v: f64) -> [usize; 3] {
    let mut c = [0usize; 3];
    for i in 0..n {
        for (k, hit) in inputs.clipped(buf, n, i, range_v).into_iter().enumerate() {
            c[k] += hit as usize;
        }
    }
    c
}

/// The input range of an NI board's QPD inputs: ±`range_v`, the sum floor (default 1 % of the
/// range) on the sum (or the four quadrants' total), and the sum's calibration.
pub fn ni_input_range(o: &NiQpdOptions) -> crate::instrument::range::InputRange {
    crate::instrument::range::InputRange::new(o.range_v, "V").with_sum(
        Some(o.sum_floor_v.unwrap_or(0.01 * o.range_v)).filter(|f| *f > 0.0),
        o.calibration.gain[2],
        o.calibration.offset_v[2],
    )
}

/// Driver settings (`[qpd]` with `backend = "nidaqmx"`).
#[derive(Debug, Clone, PartialEq)]
pub struct NiQpdOptions {
    pub library: Option<PathBuf>,
    /// The device name in NI MAX (`"Dev1"`).
    pub device: String,
    pub inputs: NiInputs,
    /// Input range ±range_v, V.
    pub range_v: f64,
    pub terminal: Terminal,
    /// Sample rate per channel, Hz.
    pub rate_hz: f64,
    /// Added to n / rate as the read's timeout.
    pub timeout_margin: Duration,
    pub calibration: Calibration,
    /// The sum input below which a pixel is dark, V (`[qpd] sum_floor`; `None`: 1 % of
    /// `range_v`; 0: not checked).
    pub sum_floor_v: Option<f64>,
}

impl Default for NiQpdOptions {
    fn default() -> Self {
        Self {
            library: None,
            device: "Dev1".into(),
            inputs: NiInputs::Signals {
                sx: "ai0".into(),
                sy: "ai1".into(),
                sum: "ai2".into(),
            },
            range_v: 10.0,
            terminal: Terminal::Diff,
            rate_hz: 800_000.0,
            timeout_margin: Duration::from_millis(1000),
            calibration: Calibration::default(),
            sum_floor_v: None,
        }
    }
}

/// A DAQmx task, stopped and cleared when dropped.
pub struct Task {
    lib: Arc<NiDaqmx>,
    handle: TaskHandle,
    device: String,
    /// For messages: `task "bfpscope-qpd"`.
    pub name: String,
}

// SAFETY: a TaskHandle is an opaque token; DAQmx functions may be called on it from any
// thread (NI-DAQmx is thread-safe), and bfpscope uses each task from one thread at a time.
unsafe impl Send for Task {}

impl Task {
    /// `DAQmxCreateTask(name, &handle)`.
    pub fn create(lib: Arc<NiDaqmx>, device: &str, name: &str) -> Result<Task, DeviceError> {
        let cname = super::vendor::c_string(device, "task name", name)?;
        let mut h: TaskHandle = std::ptr::null_mut();
        // SAFETY: `int32 DAQmxCreateTask(const char taskName[], TaskHandle *taskHandle)`.
        let r = unsafe { (lib.create_task)(cname.as_ptr(), &mut h) };
        check(&lib, device, || format!("DAQmxCreateTask(\"{name}\")"), r)?;
        Ok(Task {
            lib,
            handle: h,
            device: device.to_string(),
            name: name.to_string(),
        })
    }

    pub fn handle(&self) -> TaskHandle {
        self.handle
    }

    pub fn lib(&self) -> &NiDaqmx {
        &self.lib
    }

    /// The name a channel is created with: none (`""`), so that it is called by its physical
    /// name.
    const NO_NAME: &'static std::ffi::CStr = c"";

    fn c(&self, what: &str, s: &str) -> Result<CString, DeviceError> {
        super::vendor::c_string(&self.device, what, s)
    }

    fn check(&self, call: impl FnOnce() -> String, r: i32) -> Result<(), DeviceError> {
        check(&self.lib, &self.device, call, r)
    }

    /// `DAQmxCreateAIVoltageChan(task, physical, "", terminal, -range, range, DAQmx_Val_Volts, NULL)`.
    pub fn add_ai(
        &self,
        physical: &str,
        terminal: Terminal,
        range_v: f64,
    ) -> Result<(), DeviceError> {
        let p = self.c("channel", physical)?;
        // SAFETY: declaration of `DAQmxCreateAIVoltageChan` in NIDAQmx.h; NULL custom scale.
        let r = unsafe {
            (self.lib.create_ai_voltage_chan)(
                self.handle,
                p.as_ptr(),
                Self::NO_NAME.as_ptr(),
                terminal.daqmx(),
                -range_v,
                range_v,
                ffi::DAQMX_VAL_VOLTS,
                std::ptr::null(),
            )
        };
        self.check(
            || {
                format!(
                    "DAQmxCreateAIVoltageChan(task \"{}\", \"{physical}\", \"\", {}, {}, {}, DAQmx_Val_Volts, NULL)",
                    self.name,
                    terminal.name(),
                    -range_v,
                    range_v
                )
            },
            r,
        )
    }

    /// `DAQmxCreateAOVoltageChan(task, physical, "", min, max, DAQmx_Val_Volts, NULL)`.
    pub fn add_ao(&self, physical: &str, min_v: f64, max_v: f64) -> Result<(), DeviceError> {
        let p = self.c("channel", physical)?;
        // SAFETY: declaration of `DAQmxCreateAOVoltageChan` in NIDAQmx.h; NULL custom scale.
        let r = unsafe {
            (self.lib.create_ao_voltage_chan)(
                self.handle,
                p.as_ptr(),
                Self::NO_NAME.as_ptr(),
                min_v,
                max_v,
                ffi::DAQMX_VAL_VOLTS,
                std::ptr::null(),
            )
        };
        self.check(
            || {
                format!(
                    "DAQmxCreateAOVoltageChan(task \"{}\", \"{physical}\", \"\", {min_v}, {max_v}, DAQmx_Val_Volts, NULL)",
                    self.name
                )
            },
            r,
        )
    }

    /// `DAQmxCfgSampClkTiming(task, source, rate, DAQmx_Val_Rising, mode, samps)`; `source`
    /// empty: the board's own clock. `continuous`: `DAQmx_Val_ContSamps` (samps = buffer size).
    pub fn timing(
        &self,
        source: &str,
        rate: f64,
        continuous: bool,
        samps: u64,
    ) -> Result<(), DeviceError> {
        let s = self.c("clock source", source)?;
        let mode = if continuous {
            ffi::DAQMX_VAL_CONT_SAMPS
        } else {
            ffi::DAQMX_VAL_FINITE_SAMPS
        };
        // SAFETY: declaration of `DAQmxCfgSampClkTiming` in NIDAQmx.h.
        let r = unsafe {
            (self.lib.cfg_samp_clk_timing)(
                self.handle,
                s.as_ptr(),
                rate,
                ffi::DAQMX_VAL_RISING,
                mode,
                samps,
            )
        };
        self.check(
            || {
                format!(
                    "DAQmxCfgSampClkTiming(task \"{}\", \"{source}\", {rate}, DAQmx_Val_Rising, {}, {samps})",
                    self.name,
                    if continuous { "DAQmx_Val_ContSamps" } else { "DAQmx_Val_FiniteSamps" }
                )
            },
            r,
        )
    }

    /// `DAQmxCfgDigEdgeStartTrig(task, source, DAQmx_Val_Rising)`.
    pub fn start_trigger(&self, source: &str) -> Result<(), DeviceError> {
        let s = self.c("trigger source", source)?;
        // SAFETY: declaration of `DAQmxCfgDigEdgeStartTrig` in NIDAQmx.h.
        let r = unsafe {
            (self.lib.cfg_dig_edge_start_trig)(self.handle, s.as_ptr(), ffi::DAQMX_VAL_RISING)
        };
        self.check(
            || {
                format!(
                    "DAQmxCfgDigEdgeStartTrig(task \"{}\", \"{source}\", DAQmx_Val_Rising)",
                    self.name
                )
            },
            r,
        )
    }

    pub fn start(&self) -> Result<(), DeviceError> {
        // SAFETY: `int32 DAQmxStartTask(TaskHandle taskHandle)`.
        let r = unsafe { (self.lib.start_task)(self.handle) };
        self.check(|| format!("DAQmxStartTask(task \"{}\")", self.name), r)
    }

    pub fn stop(&self) -> Result<(), DeviceError> {
        // SAFETY: `int32 DAQmxStopTask(TaskHandle taskHandle)`.
        let r = unsafe { (self.lib.stop_task)(self.handle) };
        self.check(|| format!("DAQmxStopTask(task \"{}\")", self.name), r)
    }

    /// `DAQmxReadAnalogF64(task, n, timeout, DAQmx_Val_GroupByChannel, buf, len, &read, NULL)`:
    /// `n` samples per channel into `buf` (channels × n). Returns the samples per channel read.
    pub fn read(&self, n: usize, timeout_s: f64, buf: &mut [f64]) -> Result<usize, DeviceError> {
        let mut got: i32 = 0;
        let ni = i32::try_from(n).map_err(|_| DeviceError::Other {
            device: self.device.clone(),
            detail: format!("{n} samples per channel: at most {} per read", i32::MAX),
        })?;
        // SAFETY: declaration of `DAQmxReadAnalogF64` in NIDAQmx.h; `buf` holds
        // `arraySizeInSamps` doubles; NULL reserved.
        let r = unsafe {
            (self.lib.read_analog_f64)(
                self.handle,
                ni,
                timeout_s,
                ffi::DAQMX_VAL_GROUP_BY_CHANNEL,
                buf.as_mut_ptr(),
                buf.len() as u32,
                &mut got,
                std::ptr::null_mut(),
            )
        };
        self.check(
            || {
                format!(
                    "DAQmxReadAnalogF64(task \"{}\", {n}, {timeout_s:.3}, DAQmx_Val_GroupByChannel, buf, {}, &read, NULL)",
                    self.name,
                    buf.len()
                )
            },
            r,
        )?;
        Ok(got.max(0) as usize)
    }

    /// `DAQmxWriteAnalogF64(task, n, autoStart, timeout, DAQmx_Val_GroupByChannel, data, &written, NULL)`.
    pub fn write(
        &self,
        n: usize,
        auto_start: bool,
        timeout_s: f64,
        data: &[f64],
    ) -> Result<usize, DeviceError> {
        let mut wrote: i32 = 0;
        // SAFETY: declaration of `DAQmxWriteAnalogF64` in NIDAQmx.h; `data` holds channels × n.
        let r = unsafe {
            (self.lib.write_analog_f64)(
                self.handle,
                n as i32,
                auto_start as u32,
                timeout_s,
                ffi::DAQMX_VAL_GROUP_BY_CHANNEL,
                data.as_ptr(),
                &mut wrote,
                std::ptr::null_mut(),
            )
        };
        self.check(
            || {
                format!(
                    "DAQmxWriteAnalogF64(task \"{}\", {n}, {auto_start}, {timeout_s:.3}, DAQmx_Val_GroupByChannel, data, &written, NULL)",
                    self.name
                )
            },
            r,
        )?;
        Ok(wrote.max(0) as usize)
    }

    /// `DAQmxWriteAnalogScalarF64(task, autoStart=1, timeout, value, NULL)` (one AO channel).
    pub fn write_scalar(&self, value: f64, timeout_s: f64) -> Result<(), DeviceError> {
        // SAFETY: declaration of `DAQmxWriteAnalogScalarF64` in NIDAQmx.h.
        let r = unsafe {
            (self.lib.write_analog_scalar_f64)(
                self.handle,
                1,
                timeout_s,
                value,
                std::ptr::null_mut(),
            )
        };
        self.check(
            || {
                format!(
                    "DAQmxWriteAnalogScalarF64(task \"{}\", 1, {timeout_s:.3}, {value:.6}, NULL)",
                    self.name
                )
            },
            r,
        )
    }
}

impl Drop for Task {
    fn drop(&mut self) {
        // SAFETY: stop and clear the task we created; errors here have nowhere to go (a
        // removed device's task is gone already).
        unsafe {
            (self.lib.stop_task)(self.handle);
            (self.lib.clear_task)(self.handle);
        }
    }
}

/// Means and sample standard deviations of Sx, Sy, sum (V) over `n` samples per channel.
pub fn stats(inputs: &NiInputs, buf: &[f64], n: usize) -> ([f64; 3], [f64; 3]) {
    let mut sum = [0.0; 3];
    for i in 0..n {
        let s = inputs.signals(buf, n, i);
        for k in 0..3 {
            sum[k] += s[k];
        }
    }
    let mean = sum.map(|s| s / n.max(1) as f64);
    let mut ss = [0.0; 3];
    for i in 0..n {
        let s = inputs.signals(buf, n, i);
        for k in 0..3 {
            ss[k] += (s[k] - mean[k]).powi(2);
        }
    }
    let std = ss.map(|s| {
        if n > 1 {
            (s / (n - 1) as f64).sqrt()
        } else {
            0.0
        }
    });
    (mean, std)
}

/// A point read: means and standard deviations of Sx, Sy, sum (V), and their samples at the rail.
type VoltRead = ([f64; 3], [f64; 3], [usize; 3]);

/// The NI board as the QPD (point reads).
pub struct NiQpd {
    lib: Arc<NiDaqmx>,
    opts: NiQpdOptions,
    task: Task,
    /// Samples per channel the task is timed for.
    timed_for: Option<usize>,
    buf: Vec<f64>,
    product: String,
    serial: Option<u32>,
    overhead_sum: f64,
    reads: u32,
}

impl NiQpd {
    /// Load NI-DAQmx and create the AI task.
    pub fn open(opts: NiQpdOptions) -> Result<NiQpd, DeviceError> {
        let dev = format!("NI-DAQmx {}", opts.device);
        let lib = Arc::new(NiDaqmx::load(opts.library.as_deref(), &dev)?);
        Self::connect(lib, opts)
    }

    pub fn connect(lib: Arc<NiDaqmx>, opts: NiQpdOptions) -> Result<NiQpd, DeviceError> {
        let dev = format!("NI-DAQmx {}", opts.device);
        let (product, serial) = device_identity(&lib, &opts.device)?;
        let name = if product.is_empty() {
            dev.clone()
        } else {
            format!("NI {product} {}", opts.device)
        };
        let task = Task::create(lib.clone(), &name, "bfpscope-qpd")?;
        // A point read waits a dwell (≈ 0.1 ms) for its samples: polling for them, not
        // sleeping, keeps a busy host's wake-up latency (≈ 1 ms) out of every point
        // (`DAQmxSetReadWaitMode`, when the library has it).
        if let Some(wait) = lib.set_read_wait_mode {
            // SAFETY: `int32 DAQmxSetReadWaitMode(TaskHandle taskHandle, int32 data)`.
            let r = unsafe { wait(task.handle(), ffi::DAQMX_VAL_POLL) };
            check(
                &lib,
                &name,
                || format!("DAQmxSetReadWaitMode({}, DAQmx_Val_Poll)", task.name),
                r,
            )?;
        }
        for ch in opts.inputs.names() {
            task.add_ai(
                &format!("{}/{ch}", opts.device),
                opts.terminal,
                opts.range_v,
            )?;
        }
        let mut q = NiQpd {
            lib,
            opts,
            task,
            timed_for: None,
            buf: Vec::new(),
            product,
            serial,
            overhead_sum: 0.0,
            reads: 0,
        };
        // Time it once now, so a rate the board refuses fails at connect, not at the first read;
        // and read, so that the first scan's ETA knows what a read costs beyond its samples
        // (task start, transfer, stop: [`Qpd::overhead_s`]).
        q.time_for(2)?;
        // the first read also verifies and commits the task: only the second is timed
        q.read_volts(2)?;
        q.overhead_sum = 0.0;
        q.reads = 0;
        q.read_volts(2)?;
        Ok(q)
    }

    /// The board's product type and serial number (`DAQmxGetDevProductType`,
    /// `DAQmxGetDevSerialNum`), for the metadata.
    pub fn identity(&self) -> (String, Option<u32>) {
        (self.product.clone(), self.serial)
    }

    /// The loaded library (the raster's tasks use the same one).
    pub fn lib(&self) -> Arc<NiDaqmx> {
        self.lib.clone()
    }

    pub fn library(&self) -> String {
        self.lib.path.display().to_string()
    }

    pub fn options(&self) -> &NiQpdOptions {
        &self.opts
    }

    /// Time the task for a read of `n` samples per channel: a finite acquisition of at least
    /// 2 (DAQmx refuses `sampsPerChan` = 1: `DAQmx_SampQuant_SampPerChan` begins at 2; a read
    /// of 1 takes the first of 2).
    fn time_for(&mut self, n: usize) -> Result<(), DeviceError> {
        let n = n.max(2);
        if self.timed_for != Some(n) {
            self.task.timing("", self.opts.rate_hz, false, n as u64)?;
            self.timed_for = Some(n);
        }
        Ok(())
    }

    fn read_volts(&mut self, n: usize) -> Result<VoltRead, DeviceError> {
        if n == 0 {
            return Err(DeviceError::Other {
                device: self.name(),
                detail: "a read of 0 samples: n must be at least 1".into(),
            });
        }
        let chans = self.opts.inputs.names().len();
        self.time_for(n)?;
        self.buf.resize(chans * n, 0.0);
        let timeout = n as f64 / self.opts.rate_hz + self.opts.timeout_margin.as_secs_f64();
        let t0 = std::time::Instant::now();
        self.task.start()?;
        let r = self.task.read(n, timeout, &mut self.buf);
        // Stopped on every path, the error of the read first.
        let s = self.task.stop();
        let got = r?;
        s?;
        if got != n {
            return Err(DeviceError::Garbled {
                device: self.name(),
                command: "DAQmxReadAnalogF64".into(),
                reply: format!("{got} samples per channel read, {n} asked for"),
            });
        }
        let wall = t0.elapsed().as_secs_f64();
        self.overhead_sum += (wall - n as f64 / self.opts.rate_hz).max(0.0);
        self.reads += 1;
        let (mean, std) = stats(&self.opts.inputs, &self.buf, n);
        let clipped = clip_counts(&self.opts.inputs, &self.buf, n, self.opts.range_v);
        Ok((mean, std, clipped))
    }
}

/// `DAQmxGetDevProductType` and `DAQmxGetDevSerialNum` of `device`, when the library has them
/// (empty / None otherwise: they are for the metadata). The first call made on the board: a
/// negative code (no such device, the board removed) is an error naming the function, the
/// device and the code, and nothing else is asked of the board (no task is created).
pub fn device_identity(lib: &NiDaqmx, device: &str) -> Result<(String, Option<u32>), DeviceError> {
    let dev = format!("NI-DAQmx {device}");
    let d = CString::new(device).map_err(|_| DeviceError::Other {
        device: dev.clone(),
        detail: format!("qpd.device = {device:?}: a device name has no NUL byte"),
    })?;
    let mut product = String::new();
    if let Some(f) = lib.get_dev_product_type {
        let mut buf = vec![0 as std::os::raw::c_char; 256];
        // SAFETY: `int32 DAQmxGetDevProductType(const char device[], char *data, uInt32 bufferSize)`.
        let r = unsafe { f(d.as_ptr(), buf.as_mut_ptr(), buf.len() as u32) };
        check(
            lib,
            &dev,
            || format!("DAQmxGetDevProductType(\"{device}\", data, 256)"),
            r,
        )?;
        product = ffi::c_buf_to_string(&buf);
    }
    let mut serial = None;
    if let Some(f) = lib.get_dev_serial_num {
        let mut s: u32 = 0;
        // SAFETY: `int32 DAQmxGetDevSerialNum(const char device[], uInt32 *data)`.
        let r = unsafe { f(d.as_ptr(), &mut s) };
        check(
            lib,
            &dev,
            || format!("DAQmxGetDevSerialNum(\"{device}\", &data)"),
            r,
        )?;
        serial = Some(s);
    }
    Ok((product, serial))
}

impl Qpd for NiQpd {
    fn name(&self) -> String {
        if self.product.is_empty() {
            format!("NI-DAQmx {}", self.opts.device)
        } else {
            format!("NI {} {}", self.product, self.opts.device)
        }
    }

    fn sample_rate(&self) -> f64 {
        self.opts.rate_hz
    }

    fn read(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        let (mean, std, clipped) = self.read_volts(n)?;
        Ok(QpdReading {
            clipped,
            ..self.opts.calibration.apply(mean, std, n)
        })
    }

    fn input_range(&self) -> Option<crate::instrument::range::InputRange> {
        Some(ni_input_range(&self.opts))
    }

    fn overhead_s(&self) -> f64 {
        if self.reads == 0 {
            0.0
        } else {
            self.overhead_sum / self.reads as f64
        }
    }
}

/// PCI-6120: the highest sample rate per channel, Hz.
pub const PCI6120_MAX_RATE_HZ: f64 = 800_000.0;
/// PCI-6120: the widest input range, ±V.
pub const PCI6120_MAX_RANGE_V: f64 = 42.0;

/// An NI DAQ board through NI-DAQmx (the QPD, and the hardware-timed raster of `[raster]`). (listed in `instrument::registry`).
/// NI DAQ board through NI-DAQmx: a `[qpd]` backend (and `[raster]`).
pub const NIDAQMX: crate::instrument::family::Backend =
    crate::instrument::family::Backend("nidaqmx");

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn daqmx_messages_carry_the_name_and_the_text() {
        assert_eq!(
            format_daqmx_message(-200284, "Some or all samples requested have not yet been acquired.\nTask Name: q"),
            "DAQmxErrorSamplesNotYetAvailable: Some or all samples requested have not yet been acquired. Task Name: q"
        );
        assert_eq!(
            format_daqmx_message(-209999, ""),
            "DAQmx error (no text from DAQmxGetExtendedErrorInfo)"
        );
    }

    #[test]
    fn channel_names_are_checked() {
        assert_eq!(parse_channel("ai", "ai3", "Dev1").unwrap(), "ai3");
        assert_eq!(parse_channel("ai", "Dev1/ai0", "Dev1").unwrap(), "ai0");
        assert_eq!(parse_channel("ao", " ao1 ", "Dev1").unwrap(), "ao1");
        for bad in ["ao0", "ai", "ai-1", "ai01", "ai64", "a i0", "ai0x"] {
            let e = parse_channel("ai", bad, "Dev1").unwrap_err();
            assert!(
                e.contains(&format!("{bad:?}")) && e.contains("\"ai0\" … \"ai63\""),
                "{e}"
            );
        }
        let e = parse_channel("ai", "Dev2/ai0", "Dev1").unwrap_err();
        assert!(e.contains("\"Dev2\"") && e.contains("\"Dev1\""), "{e}");
    }

    #[test]
    fn terminals_map_to_the_header_values() {
        assert_eq!(Terminal::parse("diff").unwrap().daqmx(), 10106);
        assert_eq!(Terminal::parse("RSE").unwrap().daqmx(), 10083);
        assert_eq!(Terminal::parse("nrse").unwrap().daqmx(), 10078);
        assert_eq!(Terminal::parse("pseudodiff").unwrap().daqmx(), 12529);
        assert_eq!(Terminal::parse("default").unwrap().daqmx(), -1);
        assert!(Terminal::parse("single")
            .unwrap_err()
            .contains("\"single\""));
    }

    #[test]
    fn quadrants_form_differences_and_sum() {
        let q = NiInputs::Quadrants(["ai0", "ai1", "ai2", "ai3"].map(String::from));
        // 2 samples per channel, GroupByChannel: q1 = [1, 2], q2 = [3, 4], q3 = [5, 6], q4 = [7, 8]
        let buf = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0];
        assert_eq!(
            q.signals(&buf, 2, 0),
            [(1.0 + 7.0) - (3.0 + 5.0), (1.0 + 3.0) - (5.0 + 7.0), 16.0]
        );
        let (m, s) = stats(&q, &buf, 2);
        assert_eq!(m, [0.0, -8.0, 18.0]);
        // sum: 16 and 20, sample std = |20 − 16| / √2
        assert!((s[2] - 4.0 / 2f64.sqrt()).abs() < 1e-12);
        assert_eq!(s[0], 0.0);
        let d = NiInputs::Signals {
            sx: "ai0".into(),
            sy: "ai1".into(),
            sum: "ai2".into(),
        };
        assert_eq!(d.signals(&buf[..6], 2, 1), [2.0, 4.0, 6.0]);
    }
}
