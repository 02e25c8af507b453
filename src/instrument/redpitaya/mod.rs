//! Driver for a Red Pitaya STEMlab board (125-14, 2 inputs, or its 4-input model) as the QPD
//! digitiser, over Red Pitaya's public SCPI server (TCP port 5000, commands and replies end in
//! CR LF). Protocol as documented in `docs/hardware.md` ("Red Pitaya STEMlab"), learned from
//! Red Pitaya's command reference (`commands-acq`) and their client `redpitaya_scpi.py`.
//!
//! Acquisition model: each input has a 16384-sample ring buffer filled at 125 MS/s / decimation
//! (decimations 1, 2, 4, …, 65536). `ACQ:START` starts writing, `ACQ:TRIG <source>` arms the
//! trigger; when it fires the source reads back `DISABLED` and `ACQ:TRIG:STAT?` answers `TD`.
//! `ACQ:TRIG:DLY d` records `8192 + d` samples after the trigger, then stops; `ACQ:TRIG:FILL?`
//! answers `1` once they are written. `ACQ:TPOS?` is the buffer index of the trigger sample,
//! and `ACQ:SOUR<n>:DATA:STA:N? <start>,<n>` reads n samples from there (wrapping). Data come
//! as `ACQ:DATA:FORMAT BIN` + `ACQ:DATA:UNITS VOLTS`: an IEEE 488.2 definite-length block
//! `#<k><len><len bytes>` of big-endian `f32` volts, then CR LF.
//!
//! A point read of n samples at the nominal QPD rate r covers a window T = n / r seconds. The
//! driver records that window at the smallest decimation d (a power of two) whose full buffer
//! is at least as long, `16384 · d / 125 MHz ≥ T`, i.e. `m = round(T · 125 MHz / d)` ≤ 16384
//! samples per input (T ≤ 8.59 s at d = 65536), triggered at once (`NOW`), and returns their
//! mean and per-sample standard deviation (volts → signal through [`Calibration`]); the
//! reading's `n` is m, the samples actually averaged.
//!
//! A buffered read ([`Qpd::arm_buffered`]) records from an external trigger (`EXT_PE`, the
//! controller's trigger output on the extension connector) at the largest decimation whose
//! rate is at least the rate asked for, widened when the line would not fit the buffer.
//!
//! Every fault names the device, the command and the reply; the acquisition is then stopped
//! (`ACQ:STOP`). A query the server rejects gets no reply: the error queue (`SYST:ERR?`) is
//! read to say why.

pub mod config;
pub use config::FAMILY;
pub mod emulator;

use crate::instrument::link::{open_tcp, LineLink, Transport};
use crate::instrument::scpi::Calibration;
use crate::instrument::scpi_session::ScpiSession;
use crate::instrument::{BufferedArm, BufferedTrace, DeviceError, Qpd, QpdReading, Trigger};
use std::time::{Duration, Instant};

/// ADC sample rate at decimation 1, Hz (STEMlab 125-14).
pub const BASE_RATE_HZ: f64 = 125e6;
/// Samples per input in the acquisition buffer (`ACQ:BUF:SIZE?`).
pub const BUFFER_SAMPLES: usize = 16384;
/// Largest decimation.
pub const MAX_DECIMATION: u32 = 65536;
/// The SCPI server's TCP port.
pub const DEFAULT_PORT: u16 = 5000;
/// Largest data reply accepted (bytes): 16384 ASCII numbers of up to 12 characters, with room.
const MAX_REPLY: usize = 1 << 20;

/// The time of the sample at `ACQ:TPOS?` relative to the trigger, s, for samples `dt` s apart
/// with averaging on (`ACQ:AVG ON`): `−dt`.
///
/// Red Pitaya's FPGA (the scope module `red_pitaya_scope.v`) sums `dec` ADC samples and writes
/// their mean when the sum is complete; at the trigger it saves the write pointer of the last
/// sample written (`adc_wp_trig <= adc_wp_cur`), which `ACQ:TPOS?` returns. So the sample at
/// TPOS is the last one completed before the trigger: its averaging window ends between 0 and
/// one sample spacing before the trigger (the decimation counter restarts at `ACQ:START`, not
/// at the trigger), and its middle lies between 1.5·dt and 0.5·dt before it. The driver dates
/// it at the expected middle, `−dt`; sample `i` after it at `(i − 1)·dt`. The phase is not
/// readable over SCPI, so each line's samples carry an unknown offset within ±dt/2, the same
/// for all samples of the line. The SCPI documents say only that averaging is the default and
/// that TPOS is where the trigger occurred.
pub fn trigger_sample_time(dt: f64) -> f64 {
    -dt
}

/// Sample rate (Hz) at decimation `dec`: 125 MHz / dec.
pub fn rate_at(dec: u32) -> f64 {
    BASE_RATE_HZ / dec as f64
}

/// Is `dec` a decimation the driver uses (a power of two from 1 to 65536)?
pub fn is_decimation(dec: u32) -> bool {
    dec.is_power_of_two() && dec <= MAX_DECIMATION
}

/// Decimation and sample count for a point read over `window_s` seconds: the smallest power of
/// two `d` with `buffer · d / 125 MHz ≥ window_s`, and `m = round(window_s · 125 MHz / d)`
/// (1 ≤ m ≤ buffer). Errors name the window and the longest one the buffer holds.
pub fn point_plan(window_s: f64, buffer: usize) -> Result<(u32, usize), String> {
    if !(window_s.is_finite() && window_s > 0.0) {
        return Err(format!("read window {window_s} s: must be a positive time"));
    }
    let longest = buffer as f64 * MAX_DECIMATION as f64 / BASE_RATE_HZ;
    if window_s > longest * (1.0 + 1e-12) {
        return Err(format!(
            "read window {window_s} s: longer than the {longest:.3} s the {buffer}-sample buffer holds \
             at decimation {MAX_DECIMATION} (read fewer samples, or average several reads)"
        ));
    }
    let mut d = 1u32;
    while (buffer as f64) * (d as f64) / BASE_RATE_HZ < window_s * (1.0 - 1e-12)
        && d < MAX_DECIMATION
    {
        d *= 2;
    }
    let m = ((window_s * rate_at(d)).round() as usize).clamp(1, buffer);
    Ok((d, m))
}

/// Decimation and sample count for a buffered read of `n` samples at `rate` Hz (a line of
/// `n / rate` seconds): the largest power-of-two decimation whose rate is ≥ `rate`, raised
/// until the line fits the buffer; `m = ceil(duration · actual rate)` samples. Errors name the
/// argument, its value and the allowed range.
pub fn buffered_plan(n: usize, rate: f64, buffer: usize) -> Result<(u32, usize), String> {
    if n == 0 {
        return Err("n_samples 0: must be at least 1".into());
    }
    if !(rate.is_finite() && rate > 0.0 && rate <= BASE_RATE_HZ) {
        return Err(format!(
            "sample_rate {rate} Hz: must be between {} Hz and {BASE_RATE_HZ:e} Hz",
            rate_at(MAX_DECIMATION)
        ));
    }
    let duration = n as f64 / rate;
    let mut d = 1u32;
    while d < MAX_DECIMATION && rate_at(d * 2) >= rate * (1.0 - 1e-12) {
        d *= 2;
    }
    while (buffer as f64) / rate_at(d) < duration * (1.0 - 1e-12) {
        if d >= MAX_DECIMATION {
            return Err(format!(
                "line of {n} samples at {rate} Hz ({duration} s): longer than the {:.3} s the \
                 {buffer}-sample buffer holds at decimation {MAX_DECIMATION}",
                buffer as f64 / rate_at(MAX_DECIMATION)
            ));
        }
        d *= 2;
    }
    let m = ((duration * rate_at(d) - 1e-9).ceil() as usize).clamp(1, buffer);
    Ok((d, m))
}

pub use super::tables::{ChannelMap, InputGain};

/// Driver settings (see `[qpd]` with `backend = "redpitaya"` in `bfpscope.toml`).
#[derive(Debug, Clone, PartialEq)]
pub struct RedPitayaOptions {
    /// Reply timeout for one command, not counting the acquisition itself.
    pub timeout: Duration,
    /// Volts → signal units, per signal (Sx, Sy, Sz).
    pub calibration: Calibration,
    pub channels: ChannelMap,
    /// Nominal QPD sample rate, Hz: a point read of n samples covers n / rate seconds.
    pub sample_rate_hz: f64,
    /// Input range set on every mapped input (must match the jumpers).
    pub gain: InputGain,
    /// Interval between trigger/fill state polls.
    pub poll: Duration,
    /// The sum input below which a pixel is dark, V (`[qpd] sum_floor`; `None`: 1 % of the
    /// input range; 0: not checked).
    pub sum_floor_v: Option<f64>,
}

impl Default for RedPitayaOptions {
    fn default() -> Self {
        Self {
            timeout: Duration::from_millis(1000),
            calibration: Calibration::default(),
            channels: ChannelMap::default(),
            sample_rate_hz: 100_000.0,
            gain: InputGain::LV,
            poll: Duration::from_millis(1),
            sum_floor_v: None,
        }
    }
}

/// What the current acquisition records.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Armed {
    dec: u32,
    m: usize,
    /// Samples read before the m returned: 1 for a buffered read (the sample at `ACQ:TPOS?`,
    /// whose window precedes the trigger, see [`trigger_sample_time`]), 0 for a point read.
    lead: usize,
    source: &'static str,
    /// When the acquisition was started: it cannot be filled before `at + m / rate`.
    at: Instant,
}

/// A Red Pitaya board as the QPD digitiser.
pub struct RedPitaya {
    link: LineLink,
    opts: RedPitayaOptions,
    idn: String,
    buffer: usize,
    dec: Option<u32>,
    delay: Option<i64>,
    armed: Option<Armed>,
    last: Option<Armed>,
    /// An acquisition was started and not yet read or stopped.
    running: bool,
}

impl RedPitaya {
    /// Connect to `host:port` (TCP).
    pub fn open(host: &str, port: u16, opts: RedPitayaOptions) -> Result<Self, DeviceError> {
        let label = format!("{host}:{port}");
        let device = format!("Red Pitaya on {label}");
        let io = open_tcp(&device, &format!("tcp://{label}"), opts.timeout).map_err(|e| match e {
            DeviceError::Other { device, detail } => DeviceError::Other {
                device,
                detail: format!(
                    "{} (Red Pitaya: is the board on this network and its SCPI server started, in \
                     the web interface's Development > SCPI server? It listens on port {DEFAULT_PORT})",
                    detail.split(" (is the controller").next().unwrap_or(&detail)
                ),
            },
            other => other,
        })?;
        Self::connect(io, &label, opts)
    }

    /// Connect over any transport: `*IDN?` (must name REDPITAYA), `*CLS`, `ACQ:RST`, data as
    /// binary volts, averaging on (`ACQ:AVG ON`), `ACQ:BUF:SIZE?`, and the input range of
    /// every mapped input.
    pub fn connect(
        io: Box<dyn Transport>,
        label: &str,
        opts: RedPitayaOptions,
    ) -> Result<Self, DeviceError> {
        let mut rp = Self {
            // CR LF line ends, as the board's SCPI server expects; binary blocks up to MAX_REPLY
            link: LineLink::new(io, format!("Red Pitaya on {label}"), opts.timeout)
                .with_framing(b"\r\n", MAX_REPLY),
            opts,
            idn: String::new(),
            buffer: BUFFER_SAMPLES,
            dec: None,
            delay: None,
            armed: None,
            last: None,
            running: false,
        };
        let idn = rp.query("*IDN?")?;
        if !idn.trim().to_ascii_uppercase().starts_with("REDPITAYA") {
            return Err(DeviceError::Other {
                device: rp.link.device().to_string(),
                detail: format!(
                    "`*IDN?` answered {idn:?}: not a Red Pitaya SCPI server (expected REDPITAYA,…)"
                ),
            });
        }
        rp.idn = idn.trim().to_string();
        rp.command("*CLS")?;
        rp.command("ACQ:RST")?;
        rp.command("ACQ:DATA:FORMAT BIN")?;
        rp.command("ACQ:DATA:UNITS VOLTS")?;
        // each decimated sample the mean of the ADC samples it spans (the default, set
        // explicitly: the time base of a buffered read assumes it, see `read_buffered`)
        rp.command("ACQ:AVG ON")?;
        let b = rp.query("ACQ:BUF:SIZE?")?;
        rp.buffer = match b.trim().parse::<usize>() {
            Ok(v) if (2..=1 << 20).contains(&v) => v,
            _ => return Err(rp.link.garbled("ACQ:BUF:SIZE?", b)),
        };
        for c in rp.opts.channels.inputs().into_iter().flatten() {
            rp.command(&format!("ACQ:SOUR{c}:GAIN {}", rp.opts.gain.as_str()))?;
        }
        Ok(rp)
    }

    pub fn idn(&self) -> &str {
        &self.idn
    }

    pub fn options(&self) -> &RedPitayaOptions {
        &self.opts
    }

    /// Samples per input in the board's buffer (`ACQ:BUF:SIZE?`).
    pub fn buffer_size(&self) -> usize {
        self.buffer
    }

    /// `SYST:ERR?`; a nonzero code is a `Controller` error naming `after` ([`ScpiSession`]).
    pub fn check_error(&mut self, after: &str) -> Result<(), DeviceError> {
        self.link.check_error(after, self.opts.timeout)
    }

    /// Send a command without reply, then check the error queue ([`ScpiSession`]).
    pub fn command(&mut self, command: &str) -> Result<(), DeviceError> {
        self.link.scpi_command(command, self.opts.timeout)
    }

    /// Send a query and read its reply line ([`ScpiSession`]: a silent query asks the error
    /// queue once).
    pub fn query(&mut self, command: &str) -> Result<String, DeviceError> {
        self.link.scpi_query(command, self.opts.timeout)
    }

    /// Stop the acquisition after a fault, confirmed by the error query when the board still
    /// answers (the error returned already says what failed).
    fn stop_quietly(&mut self) {
        self.armed = None;
        self.running = false;
        let _ = self.command("ACQ:STOP");
    }

    fn arm(
        &mut self,
        dec: u32,
        m: usize,
        lead: usize,
        source: &'static str,
    ) -> Result<(), DeviceError> {
        if self.dec != Some(dec) {
            self.dec = None;
            self.command(&format!("ACQ:DEC {dec}"))?;
            self.dec = Some(dec);
        }
        // record m samples after the trigger (written after the one at TPOS, the last before
        // it): the delay counts from the half buffer
        let delay = m as i64 - (self.buffer / 2) as i64;
        if self.delay != Some(delay) {
            self.delay = None;
            self.command(&format!("ACQ:TRIG:DLY {delay}"))?;
            self.delay = Some(delay);
        }
        self.running = true;
        self.command("ACQ:START")?;
        self.command(&format!("ACQ:TRIG {source}"))?;
        self.armed = Some(Armed {
            dec,
            m,
            lead,
            source,
            at: Instant::now(),
        });
        Ok(())
    }

    /// Poll `query` until it answers `done`; `wait` (the other legal reply) keeps polling until
    /// `deadline`, anything else is garbled. Returns the last reply on timeout.
    fn poll(
        &mut self,
        query: &str,
        done: &str,
        wait: &str,
        deadline: Instant,
    ) -> Result<Result<(), String>, DeviceError> {
        loop {
            let r = self.query(query)?;
            let t = r.trim();
            if t == done {
                return Ok(Ok(()));
            }
            if t != wait {
                return Err(self.link.garbled(query, r));
            }
            if Instant::now() >= deadline {
                return Ok(Err(r));
            }
            std::thread::sleep(self.opts.poll);
        }
    }

    /// Wait for the trigger (at most `trigger_timeout`) and the buffer, then read the mapped
    /// inputs: volts per signal (Sx, Sy, Sz; None for an unmapped Sz).
    fn collect(&mut self, trigger_timeout: Duration) -> Result<[Option<Vec<f64>>; 3], DeviceError> {
        let Some(a) = self.armed else {
            return Err(DeviceError::Other {
                device: self.link.device().to_string(),
                detail: "read_buffered: nothing armed (call arm_buffered first)".into(),
            });
        };
        let t0 = Instant::now();
        match self.poll("ACQ:TRIG:STAT?", "TD", "WAIT", t0 + trigger_timeout)? {
            Ok(()) => {}
            Err(last) => {
                return Err(DeviceError::Other {
                    device: self.link.device().to_string(),
                    detail: format!(
                        "no trigger within {} ms: `ACQ:TRIG:STAT?` still answers {last:?} (source {}; \
                         acquisition stopped with ACQ:STOP){}",
                        trigger_timeout.as_millis(),
                        a.source,
                        if a.source.starts_with("EXT") {
                            ": is the controller's trigger output wired to DIO0_P (external trigger) of extension connector E1, and enabled?"
                        } else {
                            ""
                        }
                    ),
                });
            }
        }
        // the buffer fills m / rate after the trigger, and the trigger came after the start:
        // wait what is left of that time since the start (nothing when the read comes after
        // a hardware-timed line), then poll the fill flag
        let acq = Duration::from_secs_f64(a.m as f64 / rate_at(a.dec));
        std::thread::sleep((a.at + acq).saturating_duration_since(Instant::now()));
        let fill_timeout = self.opts.timeout + acq;
        match self.poll("ACQ:TRIG:FILL?", "1", "0", Instant::now() + fill_timeout)? {
            Ok(()) => {}
            Err(last) => {
                return Err(DeviceError::Other {
                    device: self.link.device().to_string(),
                    detail: format!(
                        "buffer not filled {} ms after the trigger: `ACQ:TRIG:FILL?` still answers {last:?} \
                         (acquisition stopped with ACQ:STOP)",
                        fill_timeout.as_millis()
                    ),
                });
            }
        }
        let r = self.query("ACQ:TPOS?")?;
        let tpos = match r.trim().parse::<usize>() {
            Ok(p) if p < self.buffer => p,
            _ => return Err(self.link.garbled("ACQ:TPOS?", r)),
        };
        let mut out: [Option<Vec<f64>>; 3] = [None, None, None];
        let timeout = self.opts.timeout + Duration::from_millis(a.m as u64 / 100);
        for (i, c) in self.opts.channels.inputs().into_iter().enumerate() {
            let Some(c) = c else { continue };
            let cmd = format!("ACQ:SOUR{c}:DATA:STA:N? {tpos},{}", a.m + a.lead);
            self.link.discard_input();
            self.link.send(&cmd)?;
            let block = match self.link.read_block(&cmd, timeout) {
                Ok(b) => b,
                Err(e @ DeviceError::Timeout { .. }) => {
                    return match self.check_error(&cmd) {
                        Err(c @ DeviceError::Controller { .. }) => Err(c),
                        _ => Err(e),
                    }
                }
                Err(e) => return Err(e),
            };
            let want = a.m + a.lead;
            if block.len() != 4 * want {
                return Err(self.link.garbled(
                    &cmd,
                    format!(
                        "{} bytes of data, expected {} ({} float32 samples)",
                        block.len(),
                        4 * want,
                        want
                    ),
                ));
            }
            let v: Vec<f64> = block
                .chunks_exact(4)
                .skip(a.lead)
                .map(|b| f32::from_be_bytes([b[0], b[1], b[2], b[3]]) as f64)
                .collect();
            if let Some(k) = v.iter().position(|x| !x.is_finite()) {
                return Err(self.link.garbled(
                    &cmd,
                    format!("sample {k} is {} (not a finite voltage)", v[k]),
                ));
            }
            out[i] = Some(v);
        }
        self.check_error("ACQ:SOUR<n>:DATA:STA:N?")?;
        self.running = false;
        self.last = self.armed.take();
        Ok(out)
    }

    /// Volts → calibrated signal for signal `i` (0 = Sx, 1 = Sy, 2 = Sz).
    fn to_signal(&self, i: usize, v: f64) -> f64 {
        let c = &self.opts.calibration;
        c.gain[i] * (v - c.offset_v[i])
    }

    /// One acquisition of `window` seconds started at once (`ACQ:TRIG NOW`): the means and
    /// standard deviations of the mapped inputs; `what` names the request in errors.
    fn read_window(&mut self, window: f64, what: &str) -> Result<QpdReading, DeviceError> {
        let (dec, m) =
            point_plan(window, self.buffer).map_err(|e| self.err_other(format!("{what}: {e}")))?;
        let r = self
            .arm(dec, m, 0, "NOW")
            .and_then(|()| self.collect(self.opts.timeout));
        let v = match r {
            Ok(v) => v,
            Err(e) => {
                self.stop_quietly();
                return Err(e);
            }
        };
        let mut mean = [0.0; 3];
        let mut std = [0.0; 3];
        let mut clipped = [0usize; 3];
        let fs = self.opts.gain.full_scale_v();
        for (i, ch) in v.iter().enumerate() {
            if let Some(s) = ch {
                clipped[i] = s
                    .iter()
                    .filter(|x| crate::instrument::range::at_rail(**x, fs))
                    .count();
                let (m_v, s_v) = mean_std(s);
                mean[i] = m_v;
                std[i] = s_v;
            } else {
                // not digitised: 0 signal, whatever the calibration offset
                mean[i] = self.opts.calibration.offset_v[i];
            }
        }
        Ok(QpdReading {
            clipped,
            ..self.opts.calibration.apply(mean, std, m)
        })
    }

    fn err_other(&self, detail: String) -> DeviceError {
        DeviceError::Other {
            device: self.link.device().to_string(),
            detail,
        }
    }
}

/// Mean and sample standard deviation (0 for fewer than 2 samples).
fn mean_std(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    if v.len() < 2 {
        return (mean, 0.0);
    }
    let var = v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (n - 1.0);
    (mean, var.sqrt())
}

impl Qpd for RedPitaya {
    fn name(&self) -> String {
        self.link.device().to_string()
    }

    fn sample_rate(&self) -> f64 {
        self.opts.sample_rate_hz
    }

    fn read(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        let window = n as f64 / self.opts.sample_rate_hz;
        self.read_window(
            window,
            &format!("read({n}) at {} Hz", self.opts.sample_rate_hz),
        )
    }

    /// The dwell is the acquisition window itself (decimation and samples from it).
    fn read_for(&mut self, duration_s: f64) -> Result<QpdReading, DeviceError> {
        self.read_window(duration_s, &format!("read_for({duration_s} s)"))
    }

    fn metadata(&self) -> Option<serde_json::Value> {
        Some(serde_json::json!({
            "idn": self.idn,
            "buffer_samples": self.buffer,
            "channels": self.opts.channels,
            "input_gain": self.opts.gain.as_str(),
            "last_acquisition": self.last.map(|a| serde_json::json!({
                "decimation": a.dec,
                "sample_rate_hz": rate_at(a.dec),
                "samples": a.m,
                "trigger": a.source,
            })),
        }))
    }

    /// ±1 V (LV) or ±20 V (HV), as `input_gain` says the jumpers are set; the sum floor
    /// (default 1 % of that) when Sz is digitised.
    fn input_range(&self) -> Option<crate::instrument::range::InputRange> {
        let fs = self.opts.gain.full_scale_v();
        let c = &self.opts.calibration;
        let floor = self.opts.sum_floor_v.unwrap_or(0.01 * fs);
        Some(crate::instrument::range::InputRange::new(fs, "V").with_sum(
            (self.opts.channels.inputs()[2].is_some() && floor > 0.0).then_some(floor),
            c.gain[2],
            c.offset_v[2],
        ))
    }

    fn arm_buffered(
        &mut self,
        n_samples: usize,
        sample_rate: f64,
        trigger: Trigger,
    ) -> Result<BufferedArm, DeviceError> {
        let (dec, m) = buffered_plan(n_samples, sample_rate, self.buffer - 1)
            .map_err(|e| self.err_other(format!("arm_buffered: {e}")))?;
        let source = match trigger {
            Trigger::Now => "NOW",
            Trigger::ExternalRising => "EXT_PE",
            Trigger::ExternalFalling => "EXT_NE",
        };
        if let Err(e) = self.arm(dec, m, 1, source) {
            self.stop_quietly();
            return Err(e);
        }
        Ok(BufferedArm {
            n_samples: m,
            sample_rate: rate_at(dec),
        })
    }

    fn read_buffered(&mut self, timeout: Duration) -> Result<BufferedTrace, DeviceError> {
        let dec = self.armed.map(|a| a.dec);
        let v = match self.collect(timeout) {
            Ok(v) => v,
            Err(e) => {
                self.stop_quietly();
                return Err(e);
            }
        };
        let dt = dec.map_or(0.0, |d| 1.0 / rate_at(d));
        let conv = |s: &Self, i: usize, ch: &Option<Vec<f64>>, n: usize| match ch {
            Some(v) => v.iter().map(|&x| s.to_signal(i, x)).collect(),
            None => vec![0.0; n],
        };
        let n = v[0].as_ref().map_or(0, Vec::len);
        let fs = self.opts.gain.full_scale_v();
        let rail = |ch: &Option<Vec<f64>>, k: usize| {
            ch.as_ref().is_some_and(|s| {
                s.get(k)
                    .is_some_and(|x| crate::instrument::range::at_rail(*x, fs))
            })
        };
        let mut clipped = Vec::new();
        for k in 0..n {
            let hit = [rail(&v[0], k), rail(&v[1], k), rail(&v[2], k)];
            if hit.iter().any(|h| *h) {
                clipped.resize(n, 0);
                clipped[k] = crate::instrument::range::clip_bits(hit);
            }
        }
        Ok(BufferedTrace {
            // the sample after the one at TPOS (read, then dropped): expected at 0
            t0_s: trigger_sample_time(dt) + dt,
            dt_s: dt,
            sx: conv(self, 0, &v[0], n),
            sy: conv(self, 1, &v[1], n),
            sz: conv(self, 2, &v[2], n),
            sz_measured: v[2].is_some(),
            clipped,
        })
    }

    fn stop_buffered(&mut self) -> Result<(), DeviceError> {
        self.armed = None;
        self.running = false;
        self.command("ACQ:STOP")
    }
}

/// A Red Pitaya STEMlab board over its SCPI server (the QPD), beside a PI stage. (listed in `instrument::registry`).
/// Red Pitaya STEMlab board over its SCPI server: a `[qpd]` backend.
pub const REDPITAYA: crate::instrument::family::Backend =
    crate::instrument::family::Backend("redpitaya");

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn point_plan_fits_the_buffer() {
        // 1 ms: 125 000 samples at full rate → decimation 8 (15625 samples, 131 µs·8 = 1.05 ms)
        assert_eq!(point_plan(1e-3, 16384), Ok((8, 15625)));
        // exactly one full buffer at decimation 1
        assert_eq!(point_plan(16384.0 / 125e6, 16384), Ok((1, 16384)));
        // a hair longer needs decimation 2
        assert_eq!(point_plan(16385.0 / 125e6, 16384).unwrap().0, 2);
        // the longest window: 16384 · 65536 / 125 MHz = 8.589934592 s
        assert_eq!(point_plan(8.589934592, 16384), Ok((65536, 16384)));
        let e = point_plan(9.0, 16384).unwrap_err();
        assert!(e.contains("9 s") && e.contains("8.590 s"), "{e}");
        assert!(point_plan(0.0, 16384).unwrap_err().contains("0 s"));
        let e = point_plan(f64::NAN, 16384).unwrap_err();
        assert_eq!(e, "read window NaN s: must be a positive time");
        // a very short window still reads one sample
        assert_eq!(point_plan(1e-12, 16384), Ok((1, 1)));
    }

    #[test]
    fn buffered_plan_rate_and_length() {
        // 100 kHz asked: 125 MHz / 1024 = 122.07 kHz is the slowest rate ≥ 100 kHz
        let (d, m) = buffered_plan(100, 1e5, 16384).unwrap();
        assert_eq!(d, 1024);
        assert_eq!(m, (1e-3 * 125e6 / 1024.0_f64).ceil() as usize); // 123
                                                                    // exact rates stay exact
        assert_eq!(buffered_plan(1000, 125e6 / 64.0, 16384), Ok((64, 1000)));
        // a line too long for the buffer at the asked rate is decimated further
        let (d, m) = buffered_plan(40_000, 125e6 / 64.0, 16384).unwrap();
        assert_eq!(d, 256);
        assert_eq!(m, 10_000);
        assert!(buffered_plan(0, 1e5, 16384)
            .unwrap_err()
            .contains("n_samples 0"));
        assert!(buffered_plan(10, 2e8, 16384)
            .unwrap_err()
            .contains("sample_rate"));
        let e = buffered_plan(10, -1.0, 16384).unwrap_err();
        assert!(e.starts_with("sample_rate -1 Hz: must be between"), "{e}");
    }

    #[test]
    fn channel_map_checks() {
        assert!(ChannelMap::default().check().is_ok());
        let bad = ChannelMap {
            sx: 1,
            sy: 1,
            sz: None,
        };
        assert_eq!(bad.check().unwrap_err().0, "sy");
        let bad = ChannelMap {
            sx: 1,
            sy: 2,
            sz: Some(5),
        };
        let (k, m) = bad.check().unwrap_err();
        assert_eq!(k, "sz");
        assert!(m.contains("input 5"), "{m}");
    }

    #[test]
    fn mean_std_of_known_values() {
        assert_eq!(mean_std(&[1.0, 3.0]), (2.0, 2f64.sqrt()));
        assert_eq!(mean_std(&[5.0]), (5.0, 0.0));
    }
}
