//! Driver for piezo stage controllers speaking PI's GCS 2.0 ASCII command set (E-727, E-709,
//! E-712, E-517, C-413 …) over RS-232 / USB-serial or TCP (port 50000).
//!
//! The subset used (see `docs/hardware.md`):
//!
//! | command            | reply                      | use                                   |
//! |--------------------|----------------------------|---------------------------------------|
//! | `*IDN?`            | one line                   | identify at connect                   |
//! | `ERR?`             | error code (`0` = none)    | after every command; clears the error |
//! | `SAI?`             | `1 ␠\n2 ␠\n3\n`             | axis identifiers, checked at connect  |
//! | `SVO? 1 2 3`       | `1=0 ␠\n2=0 ␠\n3=0\n`       | servo state at connect                |
//! | `SVO 1 1 2 1 3 1`  | —                          | closed-loop servo on, after the checks |
//! | `MOV 1 x 2 y 3 z`  | —                          | absolute move (controller units)      |
//! | `ONT? 1 2 3`       | `1=1 ␠\n2=1 ␠\n3=0\n`       | poll until every axis is on target    |
//! | `POS? 1 2 3`       | `1=12.3456 ␠\n2=… ␠\n3=…\n` | position                              |
//! | `TMN? 1 2 3` / `TMX? 1 2 3` | as `POS?`         | travel range                          |
//! | `STP`              | — (sets error 10)          | stop all axes                         |
//!
//! Lines end with LF. A multi-line reply marks every line but the last with a space before the
//! LF ("space before LF means more lines follow"). Controllers that answer a query naming
//! several axes for the first axis only are asked one axis per query (`POS? 1`, `POS? 2`, …).
//!
//! The driver only moves and reads: it does not check soft limits (that is `acquire/`'s
//! pre-flight), and a target outside the controller's travel comes back as the controller's
//! own error 7, "Position out of limits".

pub mod config;
pub use config::FAMILY;
pub mod emulator;
pub mod split;
mod wave;
pub use wave::{parse_gcs_array, GcsArray, LineSweep, SweepRecord, WaveCache};

use crate::instrument::link::{open_port, LineLink, Transport};
use crate::instrument::{DeviceError, Pos, Stage};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// Text of the common GCS controller error codes (PI GCS 2.0 error list).
pub fn gcs_error_text(code: i64) -> &'static str {
    match code {
        0 => "No error",
        1 => "Parameter syntax error",
        2 => "Unknown command",
        3 => "Command length out of limits or command buffer overrun",
        4 => "Error while scanning",
        5 => "Unallowable move attempted on unreferenced axis, or move attempted with servo off",
        6 => "Parameter for SGA not valid",
        7 => "Position out of limits",
        8 => "Velocity out of limits",
        9 => "Attempt to set pivot point while U, V and W not all 0",
        10 => "Controller was stopped by command",
        11 => "Parameter for SST or for one of the embedded scan algorithms out of range",
        12 => "Invalid axis combination for fast scan",
        13 => "Parameter for NAV out of range",
        14 => "Invalid analog channel",
        15 => "Invalid axis identifier",
        16 => "Unknown stage name",
        17 => "Parameter out of range",
        18 => "Invalid macro name",
        19 => "Error while recording macro",
        20 => "Macro not found",
        21 => "Axis has no brake",
        22 => "Axis identifier specified more than once",
        23 => "Illegal axis",
        24 => "Incorrect number of parameters",
        25 => "Invalid floating point number",
        26 => "Parameter missing",
        27 => "Soft limit out of range",
        54 => "Unknown parameter",
        57 => "Data recorder table does not exist",
        58 => "Source option does not exist; number too low or too high",
        59 => "Source ID (channel or axis) too low or too high",
        67 => "Not enough memory available for requested wave curve",
        70 => "The requested arrays have different lengths; query them separately",
        73 => "Motion commands are not allowed when wave generator output is active; use WGO to disable generator output",
        75 => "Generator started (WGO) without having selected a wave table (WSL)",
        77 => "Data Record Table does not hold enough recorded data",
        -1024 => "Motion error: position error too large, servo is switched off automatically",
        _ => "see the controller manual's error list",
    }
}

/// Most lines a multi-line reply may have before it is treated as garbage.
const MAX_REPLY_LINES: usize = 64;

/// Driver settings (see `[stage]` in `bfpscope.toml`).
#[derive(Debug, Clone, PartialEq)]
pub struct GcsOptions {
    /// Controller axis identifiers for x, y, z (`1 2 3` on an E-727); `None` for an axis this
    /// controller does not drive (a stage split across controllers, e.g. z on a second one).
    pub axes: [Option<String>; 3],
    /// Reply timeout for one command.
    pub timeout: Duration,
    /// Longest wait for `ONT?` to report every axis on target after a move.
    pub on_target_timeout: Duration,
    /// Interval between `ONT?` polls.
    pub poll_interval: Duration,
    /// Switch closed-loop servo on at connect (`SVO`) for the axes `SVO?` reports off.
    pub servo_on_connect: bool,
    /// Controller position units per µm (1 for PI piezo controllers, which work in µm;
    /// 0.001 for a controller configured in mm).
    pub units_per_um: f64,
    /// Ask one axis per query (`POS? 1`, then `POS? 2`, …), for controllers that answer a query
    /// naming several axes for the first one only. Also switched on at connect when the
    /// controller answers the several-axis `SVO?` that way.
    pub one_axis_per_query: bool,
    /// Wait for the end of a move with PI's single-character `#5` (motion status: one byte
    /// out, a hexadecimal bit mask of the moving axes back) instead of `ONT? 1 2 3`. A
    /// controller without `#5` (it sets error 2 and does not answer) is asked `ONT?` from then
    /// on. False: always `ONT?`.
    pub motion_status: bool,
    /// After `#5` reports the trajectory over, confirm with `ONT?` (and poll `ONT?` until the
    /// moved axes are on target). True by default: PI's documents do not say that `#5` covers
    /// the settling window. False trusts `#5` alone (not in the config file; the benchmarks
    /// use it to measure what the confirmation costs).
    pub confirm_on_target: bool,
    /// The digital output (1…3, `CTO`) wired to the digitiser's external trigger, pulsed at
    /// the first point of every hardware-timed line; `None`: not wired (no raster with an
    /// externally triggered digitiser).
    pub trigger_line: Option<u8>,
    /// Servo cycle, s, used when the controller does not answer `SPA? <axis> 0x0E000200`.
    pub servo_cycle_s: Option<f64>,
    /// Points per wave table, used when the controller does not answer `WMS?`.
    pub max_wave_points: Option<usize>,
    /// Points per data-recorder table, used when the controller does not answer its
    /// data-recorder parameters (`SPA? <axis> 0x16000200` / `0x16000300`).
    pub max_record_points: Option<usize>,
}

/// `[Some("1"), Some("2"), Some("3")]` from `["1", "2", "3"]`.
pub fn axes_xyz(ids: [&str; 3]) -> [Option<String>; 3] {
    ids.map(|s| Some(s.to_string()))
}

impl Default for GcsOptions {
    fn default() -> Self {
        Self {
            axes: axes_xyz(["1", "2", "3"]),
            timeout: Duration::from_millis(1000),
            on_target_timeout: Duration::from_millis(5000),
            poll_interval: Duration::from_millis(5),
            servo_on_connect: true,
            units_per_um: 1.0,
            one_axis_per_query: false,
            motion_status: true,
            confirm_on_target: true,
            trigger_line: None,
            servo_cycle_s: None,
            max_wave_points: None,
            max_record_points: None,
        }
    }
}

/// Values per stage axis (x, y, z) of one controller: `None` for the axes it does not drive.
pub type PerAxis<T> = [Option<T>; 3];

/// A PI GCS 2.0 controller driving some or all of the stage's x, y, z axes. With all three it
/// is a [`Stage`]; a stage split across controllers is a [`GcsSplitStage`] of several.
pub struct GcsStage {
    link: LineLink,
    opts: GcsOptions,
    idn: String,
    /// (x/y/z index, controller identifier) of the axes driven here, in x, y, z order.
    axes: Vec<(usize, String)>,
    /// The controller's `SAI?` reply at connect.
    sai: Vec<String>,
    /// `SVO?` at connect, per driven axis (before anything was switched on).
    servo_at_connect: Vec<bool>,
    /// One axis per query (configured or detected at connect).
    per_axis: bool,
    /// The last commanded target (µm) per driven axis, as sent: read with `MOV?` when unknown
    /// (at connect, after a stop), then kept. PI defines relative moves (`MVR`) on the target,
    /// not on the measured position; untouched axes are never re-commanded.
    commanded: Option<Vec<f64>>,
    /// `#5` answered (`Some(true)`), refused (`Some(false)`: `ONT?` is polled), or not tried.
    motion_status: Option<bool>,
    /// A `MOV` was sent without its `ERR?`: the wait for the end of the move reads it (see
    /// [`GcsStage::move_no_wait`]).
    error_check_pending: bool,
    /// Driven-axis indices named in the last `MOV`: the axes whose on-target state (`ONT?`)
    /// confirms the end of the move after `#5` reports the trajectory over.
    moved: Vec<usize>,
    /// Wall time of recent moves (MOV to on target), s: a running mean for the scan ETA.
    move_time: MeanTime,
    /// What the wave generator and the recorder can do, read once ([`LineScan::line_timing`](crate::instrument::LineScan::line_timing)).
    line_timing: Option<crate::instrument::line::LineTiming>,
    /// The wave tables and generator settings loaded for hardware-timed lines.
    waves: WaveCache,
    /// Bytes per second of a serial link (baud / 10, 8N1); `None` over TCP or an unknown
    /// transport. Long replies (`DRR?`) get their wire time added to the reply timeout.
    wire_bytes_per_s: Option<f64>,
}

/// A running mean of durations (exponential, weight 1/8 for the newest), for ETAs.
#[derive(Debug, Clone, Copy, Default)]
pub struct MeanTime(Option<f64>);

impl MeanTime {
    /// Add one measured duration, s.
    pub fn add(&mut self, s: f64) {
        if s.is_finite() && s >= 0.0 {
            self.0 = Some(match self.0 {
                None => s,
                Some(m) => m + (s - m) / 8.0,
            });
        }
    }
    /// The mean, s (0 before the first).
    pub fn get(&self) -> f64 {
        self.0.unwrap_or(0.0)
    }
    /// The mean, s, once there is one.
    pub fn value(&self) -> Option<f64> {
        self.0
    }
}

/// `ONT?` polls between two `ERR?` while waiting for a move to end.
pub const ERR_POLL_EVERY: usize = 10;

const XYZ: [&str; 3] = ["x", "y", "z"];

impl GcsStage {
    /// Open a port (a serial path such as `/dev/ttyUSB0` or an emulator's `/dev/pts/N`, or
    /// `tcp://HOST:50000`) and connect: identify, check the axes against `SAI?`, read `SVO?`
    /// and `MOV?`, then switch the servos on ([`GcsStage::enable`]).
    pub fn open(port: &str, baud: u32, opts: GcsOptions) -> Result<Self, DeviceError> {
        Self::open_checked(port, baud, opts)?.enabled()
    }

    /// The stage with its servos switched on ([`GcsStage::enable`]).
    fn enabled(mut self) -> Result<Self, DeviceError> {
        self.enable()?;
        Ok(self)
    }

    /// As [`GcsStage::open`] without switching anything on: the caller checks the travel range
    /// (`TMN?`/`TMX?`) against its soft limits first, then calls [`GcsStage::enable`].
    /// Dropping the stage before that leaves the controller as it was found.
    pub fn open_checked(port: &str, baud: u32, opts: GcsOptions) -> Result<Self, DeviceError> {
        let device = format!("GCS stage on {port}");
        let io = open_port(&device, port, baud, opts.timeout)?;
        let mut s = Self::connect_checked(io, port, opts)?;
        if !port.starts_with("tcp://") && baud > 0 {
            s.wire_bytes_per_s = Some(f64::from(baud) / 10.0);
        }
        Ok(s)
    }

    /// Connect over any transport and switch the servos on. `port` only labels messages.
    pub fn connect(
        io: Box<dyn Transport>,
        port: &str,
        opts: GcsOptions,
    ) -> Result<Self, DeviceError> {
        Self::connect_checked(io, port, opts)?.enabled()
    }

    /// Connect as PI's own software does, reading only: identify (`*IDN?`), clear a pending
    /// error (`ERR?`), read the axis identifiers (`SAI?`) and check the configured ones against
    /// them, read the servo state (`SVO?`) and the targets in force (`MOV?`). Nothing is
    /// switched on or moved.
    pub fn connect_checked(
        io: Box<dyn Transport>,
        port: &str,
        opts: GcsOptions,
    ) -> Result<Self, DeviceError> {
        let link = LineLink::new(io, format!("GCS stage on {port}"), opts.timeout);
        let axes: Vec<(usize, String)> = opts
            .axes
            .iter()
            .enumerate()
            .filter_map(|(i, a)| a.clone().map(|a| (i, a)))
            .collect();
        let mut s = Self {
            link,
            per_axis: opts.one_axis_per_query,
            opts,
            idn: String::new(),
            axes,
            sai: Vec::new(),
            servo_at_connect: Vec::new(),
            commanded: None,
            motion_status: None,
            error_check_pending: false,
            moved: Vec::new(),
            move_time: MeanTime::default(),
            line_timing: None,
            waves: WaveCache::default(),
            wire_bytes_per_s: None,
        };
        s.check_axes()?;
        let idn = s.query_lines("*IDN?")?.join(" ");
        s.idn = idn.trim().to_string();
        // Name the device by its model: "(c)… Physik Instrumente (PI) GmbH & Co. KG, E-727, serial, fw".
        let model = s
            .idn
            .split(',')
            .nth(1)
            .map(str::trim)
            .filter(|m| !m.is_empty());
        let label = match model {
            Some(m) => format!("PI {m} on {port}"),
            None => format!("GCS stage on {port}"),
        };
        s.link.set_device(label);
        // A stale error from before we connected is not ours: read and forget it.
        s.error_code("*IDN?")?;
        s.check_sai()?;
        // The servo state as found; a controller answering one axis per query shows it here.
        s.servo_at_connect = s.query_axes_detect("SVO?", parse_bool)?;
        // The targets in force: relative moves start from them, untouched axes keep them.
        s.commanded_partial()?;
        Ok(s)
    }

    /// Switch the closed loop on (`SVO <axis> 1`) for the axes `SVO?` found off at connect,
    /// when `servo_on_connect` is set; axes already on are not commanded.
    pub fn enable(&mut self) -> Result<(), DeviceError> {
        if !self.opts.servo_on_connect {
            return Ok(());
        }
        let off: Vec<String> = self
            .axes
            .iter()
            .zip(&self.servo_at_connect)
            .filter(|(_, on)| !**on)
            .map(|((_, id), _)| format!("{id} 1"))
            .collect();
        if off.is_empty() {
            return Ok(());
        }
        self.command(&format!("SVO {}", off.join(" ")))
    }

    /// The controller's `*IDN?` reply.
    pub fn idn(&self) -> &str {
        &self.idn
    }

    pub fn options(&self) -> &GcsOptions {
        &self.opts
    }

    /// The controller's axis identifiers (`SAI?` at connect).
    pub fn sai(&self) -> &[String] {
        &self.sai
    }

    /// Servo state per driven axis as found at connect (`SVO?`), before anything was sent.
    pub fn servo_at_connect(&self) -> PerAxis<bool> {
        let mut out = [None; 3];
        for ((i, _), on) in self.axes.iter().zip(&self.servo_at_connect) {
            out[*i] = Some(*on);
        }
        out
    }

    /// True when queries name one axis each (configured, or detected at connect).
    pub fn one_axis_per_query(&self) -> bool {
        self.per_axis
    }

    /// The stage axes (0 = x, 1 = y, 2 = z) this controller drives.
    pub fn driven(&self) -> Vec<usize> {
        self.axes.iter().map(|(i, _)| *i).collect()
    }

    fn check_axes(&self) -> Result<(), DeviceError> {
        let ids: Vec<&str> = self.axes.iter().map(|(_, a)| a.as_str()).collect();
        let bad_name = ids
            .iter()
            .any(|n| n.is_empty() || n.contains(char::is_whitespace) || n.contains('='));
        let dup = (0..ids.len()).any(|i| ids[i + 1..].contains(&ids[i]));
        if ids.is_empty() || bad_name || dup {
            return Err(DeviceError::Other {
                device: self.link.device().to_string(),
                detail: format!(
                    "invalid axis map {}: need distinct identifiers without spaces",
                    self.axis_map()
                ),
            });
        }
        Ok(())
    }

    /// `x = "1", y = "2", z = "3"` for the driven axes.
    fn axis_map(&self) -> String {
        self.axes
            .iter()
            .map(|(i, a)| format!("{} = {a:?}", XYZ[*i]))
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// `SAI?`: every configured identifier must be one of the controller's axes.
    fn check_sai(&mut self) -> Result<(), DeviceError> {
        let lines = self.query_lines("SAI?")?;
        self.sai = lines
            .iter()
            .flat_map(|l| l.split_whitespace())
            .map(str::to_string)
            .collect();
        let missing: Vec<&str> = self
            .axes
            .iter()
            .map(|(_, a)| a.as_str())
            .filter(|a| !self.sai.iter().any(|s| s == a))
            .collect();
        if missing.is_empty() {
            return Ok(());
        }
        let missing = missing.join(", ");
        // Deactivated axes are listed by `SAI? ALL` only: say so when that is the reason.
        let all = match self.query_lines("SAI? ALL") {
            Ok(l) => l
                .iter()
                .flat_map(|l| l.split_whitespace())
                .map(str::to_string)
                .collect::<Vec<_>>(),
            Err(_) => Vec::new(),
        };
        let inactive = if !all.is_empty() && all != self.sai {
            format!(" (`SAI? ALL`, deactivated axes too: {})", all.join(" "))
        } else {
            String::new()
        };
        let suggestion = if self.sai.len() >= self.axes.len() {
            let s: Vec<String> = self
                .axes
                .iter()
                .zip(&self.sai)
                .map(|((i, _), id)| format!("{} = {id:?}", XYZ[*i]))
                .collect();
            format!(", e.g. axes = {{ {} }}", s.join(", "))
        } else {
            String::new()
        };
        Err(DeviceError::Other {
            device: self.link.device().to_string(),
            detail: format!(
                "configured axes {} are not all axes of this controller: `SAI?` answered {}{inactive}; \
                 {missing} missing. Set [stage] axes in bfpscope.toml to the controller's identifiers{suggestion}",
                self.axis_map(),
                if self.sai.is_empty() {
                    "nothing".to_string()
                } else {
                    self.sai.join(" ")
                },
            ),
        })
    }

    fn axes_list(&self) -> String {
        self.axes
            .iter()
            .map(|(_, a)| a.as_str())
            .collect::<Vec<_>>()
            .join(" ")
    }

    /// Send a command that has no reply, then `ERR?`; a nonzero code is a `Controller` error
    /// naming `command`.
    pub fn command(&mut self, command: &str) -> Result<(), DeviceError> {
        self.link.discard_input();
        self.link.send(command)?;
        match self.error_code(command)? {
            0 => Ok(()),
            code => Err(self.controller_error(command, code)),
        }
    }

    fn controller_error(&self, command: &str, code: i64) -> DeviceError {
        DeviceError::Controller {
            device: self.link.device().to_string(),
            command: command.to_string(),
            code,
            message: gcs_error_text(code).to_string(),
        }
    }

    /// `ERR?`: the controller's last error code (reading it resets it to 0). `after` names
    /// the command the code refers to, for messages.
    pub fn error_code(&mut self, after: &str) -> Result<i64, DeviceError> {
        let label = format!("ERR? (after `{after}`)");
        let line = self
            .link
            .query_with_timeout("ERR?", self.opts.timeout)
            .map_err(|e| e.during(&label))?;
        let t = line.trim();
        t.parse::<i64>()
            .map_err(|_| self.link.garbled(&label, line.clone()))
    }

    /// Send a query and read its (possibly multi-line) reply: lines ending in a space are
    /// followed by more. The marker spaces are removed.
    ///
    /// A controller does not answer a query it rejects (it sets its error instead), so on a
    /// timeout the driver asks `ERR?` once: a nonzero code turns the timeout into a
    /// `Controller` error naming the query.
    pub fn query_lines(&mut self, command: &str) -> Result<Vec<String>, DeviceError> {
        self.query_lines_within(command, self.opts.timeout, MAX_REPLY_LINES, |lines| {
            lines.join("\\n")
        })
    }

    /// [`query_lines`](Self::query_lines) waiting at most `timeout` for each line: a reply
    /// still going on after `max_lines` lines is `Garbled`, with what `too_many` makes of them.
    fn query_lines_within(
        &mut self,
        command: &str,
        timeout: Duration,
        max_lines: usize,
        too_many: impl FnOnce(&[String]) -> String,
    ) -> Result<Vec<String>, DeviceError> {
        self.link.discard_input();
        self.link.send(command)?;
        let mut lines = Vec::new();
        loop {
            let line = match self.link.read_line(command, timeout) {
                Ok(l) => l,
                Err(e @ DeviceError::Timeout { .. }) if lines.is_empty() => {
                    return Err(match self.error_code(command) {
                        Ok(code) if code != 0 => self.controller_error(command, code),
                        _ => e,
                    });
                }
                Err(e) => return Err(e),
            };
            let more = line.ends_with(' ');
            lines.push(line.trim_end().to_string());
            if !more {
                return Ok(lines);
            }
            if lines.len() >= max_lines {
                return Err(self.link.garbled(command, too_many(&lines)));
            }
        }
    }

    /// Parse `ID=value` lines answering `cmd`, which asked for the driven axes `asked`
    /// (indices into `self.axes`): every asked axis exactly once, nothing else.
    fn parse_axis_lines<T>(
        &self,
        cmd: &str,
        lines: &[String],
        asked: &[usize],
        parse: &impl Fn(&str) -> Option<T>,
    ) -> Result<Vec<T>, DeviceError> {
        let whole = || lines.join("\\n");
        let mut out: Vec<Option<T>> = asked.iter().map(|_| None).collect();
        for line in lines {
            let (key, value) = line
                .split_once('=')
                .ok_or_else(|| self.link.garbled(cmd, whole()))?;
            let k = asked
                .iter()
                .position(|&j| self.axes[j].1 == key.trim())
                .ok_or_else(|| self.link.garbled(cmd, whole()))?;
            let v = parse(value.trim()).ok_or_else(|| self.link.garbled(cmd, whole()))?;
            if out[k].is_some() {
                return Err(self.link.garbled(cmd, whole()));
            }
            out[k] = Some(v);
        }
        out.into_iter()
            .map(|v| v.ok_or_else(|| self.link.garbled(cmd, whole())))
            .collect()
    }

    /// Query `CMD? 1 2 3` (or `CMD? 1`, `CMD? 2`, … one axis per query) and parse the
    /// `ID=value` lines, in the order of the driven axes.
    fn query_axes<T>(
        &mut self,
        command: &str,
        parse: impl Fn(&str) -> Option<T>,
    ) -> Result<Vec<T>, DeviceError> {
        if self.per_axis {
            let mut out = Vec::with_capacity(self.axes.len());
            for k in 0..self.axes.len() {
                out.extend(self.query_one_axis(command, k, &parse)?);
            }
            return Ok(out);
        }
        let cmd = format!("{command} {}", self.axes_list());
        let lines = self.query_lines(&cmd)?;
        let all: Vec<usize> = (0..self.axes.len()).collect();
        self.parse_axis_lines(&cmd, &lines, &all, &parse)
    }

    fn query_one_axis<T>(
        &mut self,
        command: &str,
        k: usize,
        parse: &impl Fn(&str) -> Option<T>,
    ) -> Result<Vec<T>, DeviceError> {
        let cmd = format!("{command} {}", self.axes[k].1);
        let lines = self.query_lines(&cmd)?;
        self.parse_axis_lines(&cmd, &lines, &[k], parse)
    }

    /// As [`Self::query_axes`], and a controller that answers the several-axis query with the
    /// first axis alone (one `ID=value` line naming it) is switched to one axis per query, the
    /// remaining axes asked one by one. Used once, at connect.
    fn query_axes_detect<T>(
        &mut self,
        command: &str,
        parse: impl Fn(&str) -> Option<T>,
    ) -> Result<Vec<T>, DeviceError> {
        if self.per_axis || self.axes.len() < 2 {
            return self.query_axes(command, parse);
        }
        let cmd = format!("{command} {}", self.axes_list());
        let lines = self.query_lines(&cmd)?;
        let first_only = lines.len() == 1
            && lines[0]
                .split_once('=')
                .is_some_and(|(k, _)| k.trim() == self.axes[0].1);
        if !first_only {
            let all: Vec<usize> = (0..self.axes.len()).collect();
            return self.parse_axis_lines(&cmd, &lines, &all, &parse);
        }
        self.per_axis = true;
        let mut out = self.parse_axis_lines(&cmd, &lines, &[0], &parse)?;
        for k in 1..self.axes.len() {
            out.extend(self.query_one_axis(command, k, &parse)?);
        }
        Ok(out)
    }

    fn query_positions(&mut self, command: &str) -> Result<Vec<f64>, DeviceError> {
        let k = self.opts.units_per_um;
        let v = self.query_axes(command, |s| s.parse::<f64>().ok().filter(|v| v.is_finite()))?;
        Ok(v.into_iter().map(|v| v / k).collect())
    }

    /// Driven-axis values to x, y, z (None for the axes driven elsewhere).
    fn per_axis_of<T: Copy>(&self, v: &[T]) -> PerAxis<T> {
        let mut out = [None; 3];
        for ((i, _), x) in self.axes.iter().zip(v) {
            out[*i] = Some(*x);
        }
        out
    }

    /// All three axes, or an error naming the ones this controller does not drive.
    fn full<T: Copy>(&self, v: PerAxis<T>, what: &str) -> Result<[T; 3], DeviceError> {
        match v {
            [Some(x), Some(y), Some(z)] => Ok([x, y, z]),
            _ => Err(DeviceError::Other {
                device: self.link.device().to_string(),
                detail: format!(
                    "{what}: this controller drives only {} (a stage split across controllers is a GcsSplitStage)",
                    self.axis_map()
                ),
            }),
        }
    }

    fn require_all(&self, what: &str) -> Result<(), DeviceError> {
        self.full(self.per_axis_of(&[(); 3]), what).map(|_| ())
    }

    /// A query of positions-like values (`POS?`, `MOV?`, `TMN?`, `VEL?`…), µm, per x, y, z.
    pub fn read_axes(&mut self, command: &str) -> Result<PerAxis<f64>, DeviceError> {
        let v = self.query_positions(command)?;
        Ok(self.per_axis_of(&v))
    }

    /// `ONT?`: on-target state of x, y, z (axes not driven here count as on target).
    pub fn on_target(&mut self) -> Result<[bool; 3], DeviceError> {
        let v = self.query_axes("ONT?", parse_bool)?;
        Ok(self.per_axis_of(&v).map(|b| b.unwrap_or(true)))
    }

    /// Poll `ONT?` until every axis is on target, at most `on_target_timeout` after `after`.
    pub fn wait_on_target(&mut self, after: &str) -> Result<(), DeviceError> {
        self.wait_on_target_or_abort(after, None).map(|_| ())
    }

    /// As [`Self::wait_on_target`]; returns `Ok(false)` as soon as `abort` is raised (Ctrl-C),
    /// without stopping anything: the caller sends the stop.
    ///
    /// With `#5` the wait has two phases. `#5` (one byte each way) is polled while the
    /// trajectory runs; once it reports no axis in motion, the axes the `MOV` named are asked
    /// `ONT?` (PI: on target = inside the settling window, parameter 0x07000900, for at least
    /// the settling time, 0x07000901; E-727 manual E727T0005, "On Target" trigger mode), and
    /// from then on `ONT?` is polled until they are on target: PI's documents do not say that
    /// `#5` covers the settling window, and PIPython's `waitontarget` asks `ONT?` too. Without
    /// `#5`, `ONT?` is polled for all driven axes from the start.
    pub fn wait_on_target_or_abort(
        &mut self,
        after: &str,
        abort: Option<&AtomicBool>,
    ) -> Result<bool, DeviceError> {
        let t0 = Instant::now();
        let mut polls = 0usize;
        // `#5` has reported the trajectory over: on-target is now asked with `ONT?`
        let mut settling = false;
        loop {
            let (ont, via) = if settling {
                let idx = self.moved_or_all();
                (self.on_target_of(&idx)?, self.ont_query_text(&idx))
            } else {
                self.poll_motion()?
            };
            let done = ont.iter().all(|&(_, b)| b);
            if done && via == "#5" && self.opts.confirm_on_target {
                // the trajectory is over: confirm with `ONT?` at once
                settling = true;
                continue;
            }
            if done || (settling && self.error_check_pending) {
                // the `ERR?` owed for a `MOV` sent without it: read once the trajectory is
                // over, whether or not the axes have settled (a tripped servo, −1024, stops
                // the axis off target: reported as itself, not after the timeout)
                if std::mem::take(&mut self.error_check_pending) {
                    let code = self.error_code(after)?;
                    if code != 0 {
                        self.commanded = None;
                        return Err(self.controller_error(after, code));
                    }
                }
                if done {
                    return Ok(true);
                }
            }
            if abort.is_some_and(|a| a.load(Ordering::SeqCst)) {
                return Ok(false);
            }
            polls += 1;
            let timed_out = t0.elapsed() >= self.opts.on_target_timeout;
            // Asynchronous errors (e.g. −1024, the servo tripped) surface only in ERR?: read it
            // every ERR_POLL_EVERY polls and when the wait ends badly, so a servo trip is
            // reported as itself, not as "not on target".
            if timed_out || polls.is_multiple_of(ERR_POLL_EVERY) {
                let code = self.error_code(after)?;
                if code != 0 {
                    self.error_check_pending = false;
                    self.commanded = None;
                    return Err(self.controller_error(after, code));
                }
            }
            if timed_out {
                let state: Vec<String> = ont
                    .iter()
                    .map(|&(j, b)| format!("{}={}", self.axes[j].1, u8::from(b)))
                    .collect();
                let trajectory = if settling {
                    " (`#5` reported the trajectory over: the axes did not settle within the \
                     controller's settling window)"
                } else {
                    ""
                };
                return Err(DeviceError::Other {
                    device: self.link.device().to_string(),
                    detail: format!(
                        "not on target within {} ms after `{after}` (last `{via}` reply: {}){trajectory}",
                        self.opts.on_target_timeout.as_millis(),
                        state.join(" ")
                    ),
                });
            }
            std::thread::sleep(self.opts.poll_interval);
        }
    }

    /// The driven axes the last `MOV` named (all driven axes when none is known).
    fn moved_or_all(&self) -> Vec<usize> {
        if self.moved.is_empty() {
            (0..self.axes.len()).collect()
        } else {
            self.moved.clone()
        }
    }

    /// How the `ONT?` of driven axes `idx` is sent (the last query when one axis per query).
    fn ont_query_text(&self, idx: &[usize]) -> String {
        let ids: Vec<&str> = idx.iter().map(|&j| self.axes[j].1.as_str()).collect();
        if self.per_axis {
            format!("ONT? {}", ids.last().copied().unwrap_or(""))
        } else {
            format!("ONT? {}", ids.join(" "))
        }
    }

    /// `ONT?` for the driven axes `idx` (one query, or one per axis): (index, on target).
    fn on_target_of(&mut self, idx: &[usize]) -> Result<Vec<(usize, bool)>, DeviceError> {
        if self.per_axis {
            let mut out = Vec::with_capacity(idx.len());
            for &k in idx {
                out.extend(
                    self.query_one_axis("ONT?", k, &parse_bool)?
                        .into_iter()
                        .map(|b| (k, b)),
                );
            }
            return Ok(out);
        }
        let ids: Vec<&str> = idx.iter().map(|&j| self.axes[j].1.as_str()).collect();
        let cmd = format!("ONT? {}", ids.join(" "));
        let lines = self.query_lines(&cmd)?;
        let v = self.parse_axis_lines(&cmd, &lines, idx, &parse_bool)?;
        Ok(idx.iter().copied().zip(v).collect())
    }

    /// Whether the driven axes are done moving: `#5` where the controller answers it (the
    /// trajectory), else `ONT?` of all driven axes. Returns (driven-axis index, not in motion /
    /// on target) per driven axis and the query used.
    fn poll_motion(&mut self) -> Result<(Vec<(usize, bool)>, String), DeviceError> {
        if self.opts.motion_status && self.motion_status != Some(false) {
            match self.query_motion_status() {
                Ok(v) => {
                    self.motion_status = Some(true);
                    return Ok((v.into_iter().enumerate().collect(), "#5".into()));
                }
                // the first `#5` refused as unknown (error 2): a controller without it
                Err(DeviceError::Controller { code: 2, .. }) if self.motion_status.is_none() => {
                    self.motion_status = Some(false);
                }
                Err(e) => return Err(e),
            }
        }
        let all: Vec<usize> = (0..self.axes.len()).collect();
        let text = self.ont_query_text(&all);
        Ok((self.on_target_of(&all)?, text))
    }

    /// `#5` (the single byte 0x05, no line end): the controller answers the motion status as a
    /// hexadecimal bit mask, bit 0 for the first axis of `SAI?`, bit 1 the second, … ("5":
    /// the first and third axes are moving). Returns per driven axis: not in motion. A reply
    /// that is not hexadecimal is `Garbled` naming `#5`; no reply is a `Timeout`, or the
    /// controller's error when `ERR?` holds one (2: the controller has no `#5`).
    pub fn query_motion_status(&mut self) -> Result<Vec<bool>, DeviceError> {
        const CMD: &str = "#5";
        self.link.discard_input();
        self.link.send_raw(&[0x05], CMD)?;
        let line = match self.link.read_line(CMD, self.opts.timeout) {
            Ok(l) => l,
            Err(e @ DeviceError::Timeout { .. }) => {
                return Err(match self.error_code(CMD) {
                    Ok(code) if code != 0 => self.controller_error(CMD, code),
                    _ => e,
                })
            }
            Err(e) => return Err(e),
        };
        let t = line.trim();
        let mask = (!t.is_empty() && t.len() <= 16)
            .then(|| u64::from_str_radix(t, 16).ok())
            .flatten()
            .ok_or_else(|| self.link.garbled(CMD, line.clone()))?;
        self.axes
            .iter()
            .map(|(_, id)| match self.sai.iter().position(|s| s == id) {
                Some(bit) if bit < 64 => Ok(mask & (1u64 << bit) == 0),
                _ => Err(self.link.garbled(CMD, line.clone())),
            })
            .collect()
    }

    /// How motion is polled: `"#5"`, `"ONT?"` (configured, or `#5` refused), or `None`
    /// before the first move.
    pub fn motion_query(&self) -> Option<&'static str> {
        match (self.opts.motion_status, self.motion_status) {
            (false, _) | (true, Some(false)) => Some("ONT?"),
            (true, Some(true)) => Some("#5"),
            (true, None) => None,
        }
    }

    /// Running mean wall time of a move (`MOV` to on target), s; 0 before the first.
    pub fn mean_move_s(&self) -> f64 {
        self.move_time.get()
    }

    /// What a point scan's move (one axis, a step of the grid) costs on this link before any
    /// move was measured, s (the first scan after connecting): the exchange
    /// [`move_to`](Stage::move_to) makes — `MOV 1 -0.400000` (16 bytes) written; `#5` (1 byte,
    /// reply `0`+LF) twice, the first seeing the trajectory still running (a piezo step takes
    /// milliseconds, longer than one turnaround), one poll interval between them; `ONT? 1` (7
    /// bytes, `1=1`+LF back) to confirm the settling window; the `ERR?` owed for the `MOV` (5
    /// bytes, `0`+LF) — each reply costing the link's latency measured on every reply so far
    /// (the connect's identification and configuration queries) plus its bytes at the
    /// configured baud rate (10 bits per byte; none over TCP). Longer settling shows after the
    /// first row, when the engine revises the ETA from the measured cost. 0 before any reply.
    pub fn move_time_prior_s(&self) -> f64 {
        let Some(lat) = self.link.latency_s(self.wire_bytes_per_s) else {
            return 0.0;
        };
        let wire = |bytes: f64| self.wire_bytes_per_s.map_or(0.0, |r| bytes / r);
        let reply = |out: f64, back: f64| lat + wire(out + back);
        let ont = reply(7.0, 4.0);
        let polls = if self.opts.motion_status && self.motion_status != Some(false) {
            2.0 * reply(1.0, 2.0)
                + if self.opts.confirm_on_target {
                    ont
                } else {
                    0.0
                }
        } else {
            2.0 * ont
        };
        wire(16.0) + polls + self.opts.poll_interval.as_secs_f64() + reply(5.0, 2.0)
    }

    /// The link's per-command costs since the last call.
    pub fn take_link_costs(&mut self) -> crate::instrument::link::LinkCosts {
        self.link.take_costs()
    }

    /// `SVO <axis> s` for every driven axis.
    pub fn set_servo(&mut self, on: bool) -> Result<(), DeviceError> {
        let s = u8::from(on);
        let cmd = self
            .axes
            .iter()
            .map(|(_, a)| format!("{a} {s}"))
            .collect::<Vec<_>>()
            .join(" ");
        self.command(&format!("SVO {cmd}"))
    }

    /// The last commanded target (µm) of the driven axes: `MOV?` when not known yet, then what
    /// was sent.
    pub fn commanded_partial(&mut self) -> Result<PerAxis<f64>, DeviceError> {
        let t = self.commanded_vec()?;
        Ok(self.per_axis_of(&t))
    }

    /// The commanded targets per driven axis, read with `MOV?` when unknown.
    fn commanded_vec(&mut self) -> Result<Vec<f64>, DeviceError> {
        if let Some(t) = &self.commanded {
            return Ok(t.clone());
        }
        let t = self.query_positions("MOV?")?;
        self.commanded = Some(t.clone());
        Ok(t)
    }

    /// The last commanded target (µm) of x, y, z (all three driven here).
    pub fn commanded_target(&mut self) -> Result<Pos, DeviceError> {
        let t = self.commanded_partial()?;
        self.full(t, "MOV?")
    }

    /// `MOV` for the driven axes whose target changes, without waiting (positions in µm; the
    /// entries of axes driven elsewhere are ignored). An axis whose target, as sent (6 decimals
    /// of controller units), equals its last commanded target is not named, so the targets of
    /// untouched axes never wander. Returns the command sent, or `None` when no axis changes.
    pub fn move_no_wait(&mut self, target: Pos) -> Result<Option<String>, DeviceError> {
        if self.axes.iter().any(|(i, _)| !target[*i].is_finite()) {
            return Err(DeviceError::Other {
                device: self.link.device().to_string(),
                detail: format!("refusing to send a non-finite target {target:?} µm"),
            });
        }
        let now = self.commanded_vec()?;
        let k = self.opts.units_per_um;
        let sent = |v: f64| format!("{:.6}", v * k);
        // (driven-axis index, value as sent) for the axes whose target changes
        let changed: Vec<(usize, String)> = self
            .axes
            .iter()
            .enumerate()
            .map(|(j, (i, _))| (j, sent(target[*i])))
            .filter(|(j, v)| *v != sent(now[*j]))
            .collect();
        if changed.is_empty() {
            return Ok(None);
        }
        let parts: Vec<String> = changed
            .iter()
            .map(|(j, v)| format!("{} {v}", self.axes[*j].1))
            .collect();
        let cmd = format!("MOV {}", parts.join(" "));
        self.moved = changed.iter().map(|(j, _)| *j).collect();
        // unknown until the controller has accepted it (an error leaves the old targets)
        self.commanded = None;
        if self.opts.motion_status && self.motion_status == Some(true) {
            // With `#5` the `ERR?` comes once the motion has ended: it reports a refused `MOV`
            // (which does not move, so `#5` answers 0 at once) and an error during the move
            // (−1024, the servo tripped: the axis stops and `#5` answers 0 too) alike, in one
            // round trip per move. Until `#5` has answered once, `MOV` is followed by its
            // `ERR?` at once (a controller without `#5` overwrites the error register with 2).
            self.link.discard_input();
            self.link.send(&cmd)?;
            self.error_check_pending = true;
        } else {
            self.command(&cmd)?;
        }
        let mut t = now;
        for (j, v) in &changed {
            t[*j] = v.parse::<f64>().unwrap_or(target[self.axes[*j].0] * k) / k;
        }
        self.commanded = Some(t);
        Ok(Some(cmd))
    }

    /// `VEL <axis> v …` for the driven axes (controller units per s), then `ERR?`.
    pub fn send_velocity(&mut self, um_s: f64) -> Result<(), DeviceError> {
        if !(um_s.is_finite() && um_s > 0.0) {
            return Err(DeviceError::Other {
                device: self.link.device().to_string(),
                detail: format!("refusing to send a velocity of {um_s} µm/s"),
            });
        }
        let v = format!("{:.6}", um_s * self.opts.units_per_um);
        let cmd = format!(
            "VEL {}",
            self.axes
                .iter()
                .map(|(_, a)| format!("{a} {v}"))
                .collect::<Vec<_>>()
                .join(" ")
        );
        self.command(&cmd)
    }

    /// `STP`, then `ERR?`: error 10 ("stopped by command") is the expected answer and is
    /// cleared; any other nonzero code is reported.
    pub fn send_stop(&mut self) -> Result<(), DeviceError> {
        // where the axes stop is where the controller says their targets are now
        self.commanded = None;
        self.error_check_pending = false;
        self.link.discard_input();
        self.link.send("STP")?;
        match self.error_code("STP")? {
            0 | 10 => Ok(()),
            code => Err(self.controller_error("STP", code)),
        }
    }

    /// A GCS query: a command word ending in `?` with its arguments (`SAI?`, `POS? 1`,
    /// `*IDN?`, `VEL?`). Everything else is refused before anything is sent: motion goes
    /// through the engine.
    pub fn query_only(&mut self, query: &str) -> Result<Vec<String>, DeviceError> {
        let q = query.trim();
        let word = q.split_whitespace().next().unwrap_or("");
        let safe_chars = q
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || " ?*._-".contains(c));
        if !(word.ends_with('?') && safe_chars) {
            return Err(DeviceError::Other {
                device: self.link.device().to_string(),
                detail: format!(
                    "`{q}` is not a query: only GCS queries (a command ending in `?`) are sent from the prompt; moves go through mv, mvr and the scans"
                ),
            });
        }
        self.query_lines(q)
    }
}

fn parse_bool(s: &str) -> Option<bool> {
    match s {
        "1" => Some(true),
        "0" => Some(false),
        _ => None,
    }
}

impl Stage for GcsStage {
    fn name(&self) -> String {
        self.link.device().to_string()
    }

    fn position(&mut self) -> Result<Pos, DeviceError> {
        let p = self.read_axes("POS?")?;
        self.full(p, "POS?")
    }

    fn target(&mut self) -> Result<Pos, DeviceError> {
        self.commanded_target()
    }

    fn enable(&mut self) -> Result<(), DeviceError> {
        GcsStage::enable(self)
    }

    fn set_velocity(&mut self, um_s: f64) -> Result<(), DeviceError> {
        self.send_velocity(um_s)
    }

    fn velocity(&mut self) -> Result<Option<Pos>, DeviceError> {
        let v = self.read_axes("VEL?")?;
        self.full(v, "VEL?").map(Some)
    }

    fn move_to(&mut self, target: Pos) -> Result<(), DeviceError> {
        self.require_all("MOV")?;
        let t0 = Instant::now();
        match self.move_no_wait(target)? {
            Some(cmd) => {
                self.wait_on_target(&cmd)?;
                self.move_time.add(t0.elapsed().as_secs_f64());
                Ok(())
            }
            None => Ok(()),
        }
    }

    fn move_to_or_abort(&mut self, target: Pos, abort: &AtomicBool) -> Result<bool, DeviceError> {
        self.require_all("MOV")?;
        match self.move_no_wait(target)? {
            Some(cmd) => self.wait_on_target_or_abort(&cmd, Some(abort)),
            None => Ok(true),
        }
    }

    /// The running mean of the moves measured; before the first, the link model's
    /// [`GcsStage::move_time_prior_s`].
    fn move_time_s(&self) -> f64 {
        self.move_time
            .value()
            .unwrap_or_else(|| self.move_time_prior_s())
    }

    fn link_costs(&mut self) -> crate::instrument::link::LinkCosts {
        self.link.take_costs()
    }

    fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError> {
        let lo = self.read_axes("TMN?")?;
        let hi = self.read_axes("TMX?")?;
        let (lo, hi) = (self.full(lo, "TMN?")?, self.full(hi, "TMX?")?);
        Ok([(lo[0], hi[0]), (lo[1], hi[1]), (lo[2], hi[2])])
    }

    fn stop(&mut self) -> Result<(), DeviceError> {
        self.send_stop()
    }

    crate::instrument::stage_capabilities!(Lines, RawQuery);
}

/// The wave generator and the data recorder: hardware-timed raster lines.
impl crate::instrument::LineScan for GcsStage {
    /// The line timing, refused without a configured trigger output: a raster needs the
    /// controller to start the digitiser (`[stage] trigger_line`, wired to its external trigger).
    fn line_timing(&mut self) -> Result<Option<crate::instrument::line::LineTiming>, DeviceError> {
        if self.opts.trigger_line.is_none() {
            return Err(DeviceError::Other {
                device: self.link.device().to_string(),
                detail: "a raster needs the controller's trigger output wired to the digitiser's \
                         external trigger: set `[stage] trigger_line` (1…3, the OUT line wired)"
                    .into(),
            });
        }
        self.read_line_timing().map(Some)
    }
    /// A line's exchange beyond the wave, from the link model (the connect's latency, the
    /// configured baud): `WGO g 1` and its `ERR?`; the `#9` poll that sees the generator
    /// stopped, one poll interval late at most; `DRL? 1 2` (two lines back); `DRR? 1 n 1 2`
    /// answered by a GCS array: a header of ~200 bytes (`# KEY = VALUE` lines: VERSION, TYPE,
    /// SEPARATOR, DIM, SAMPLE_TIME, NDATA, a NAME per table, END_HEADER) and a row per recorded
    /// sample of two positions with six decimals, a space and the line end (~20 bytes), for
    /// the line's `n` samples. ([`read_record`](GcsStage::read_record)'s timeout allows 300 and
    /// 24, generously.) On a serial link the readout dominates: 20 bytes a sample at 115200
    /// baud is 1.7 ms per recorded sample.
    fn line_overhead_s(&self, s: &crate::instrument::line::LineSweep) -> f64 {
        let Some(lat) = self.link.latency_s(self.wire_bytes_per_s) else {
            return 0.0;
        };
        let wire = |bytes: f64| self.wire_bytes_per_s.map_or(0.0, |r| bytes / r);
        let reply = |out: f64, back: f64| lat + wire(out + back);
        let n = s.samples() as f64;
        wire(8.0)
            + reply(5.0, 2.0)
            + reply(1.0, 2.0)
            + self.opts.poll_interval.as_secs_f64()
            + reply(10.0, 16.0)
            + reply(16.0, 200.0 + 20.0 * n)
    }
    fn configure_line(&mut self, s: &LineSweep) -> Result<(), DeviceError> {
        self.wave_configure(s)
    }
    fn start_line(&mut self, s: &LineSweep) -> Result<(), DeviceError> {
        self.wave_start(s)
    }
    fn wait_line(&mut self, s: &LineSweep, abort: &AtomicBool) -> Result<bool, DeviceError> {
        self.wave_wait(s, abort)
    }
    fn read_line_record(&mut self, s: &LineSweep) -> Result<SweepRecord, DeviceError> {
        self.read_record(s.samples())
    }
    fn stop_line(&mut self, s: &LineSweep) -> Result<(), DeviceError> {
        self.wave_stop(s)
    }
}

/// Raw GCS queries at the prompt (`gcs_query`).
impl crate::instrument::RawQuery for GcsStage {
    fn raw_query(&mut self, query: &str) -> Result<Vec<String>, DeviceError> {
        self.query_only(query)
    }
}

/// PI GCS 2.0 piezo controllers (the stage), with a SCPI digitiser unless another is named. (listed in `instrument::registry`).
/// PI GCS 2.0 piezo controller(s): a `[stage]` backend.
pub const GCS: crate::instrument::family::Backend = crate::instrument::family::Backend("gcs");

#[cfg(test)]
mod tests {
    use super::*;
    use crate::instrument::link::mock::Scripted;
    use proptest::prelude::*;

    fn opts() -> GcsOptions {
        GcsOptions {
            timeout: Duration::from_millis(10),
            on_target_timeout: Duration::from_millis(30),
            poll_interval: Duration::from_millis(1),
            servo_on_connect: false,
            ..Default::default()
        }
    }

    /// Replies to the connect sequence of an E-727 with axes 1 2 3, servos on.
    fn connect_replies() -> Vec<Vec<u8>> {
        vec![
            b"(c)2026 Physik Instrumente (PI) GmbH & Co. KG, E-727, 1, 1\n".to_vec(),
            b"0\n".to_vec(),
            b"1 \n2 \n3\n".to_vec(),
            b"1=1 \n2=1 \n3=1\n".to_vec(),
            b"1=0.000000 \n2=0.000000 \n3=0.000000\n".to_vec(),
        ]
    }

    fn stage(replies: Vec<&[u8]>) -> GcsStage {
        let mut all = connect_replies();
        all.extend(replies.into_iter().map(|r| r.to_vec()));
        GcsStage::connect(Box::new(Scripted::new(all)), "mock", opts()).unwrap()
    }

    #[test]
    fn multi_line_reply_and_name() {
        let mut s = stage(vec![b"1=1.5 \n2=-2.25 \n3=10\n"]);
        assert_eq!(s.name(), "PI E-727 on mock");
        assert_eq!(s.sai(), ["1", "2", "3"]);
        assert_eq!(s.servo_at_connect(), [Some(true); 3]);
        assert_eq!(s.position().unwrap(), [1.5, -2.25, 10.0]);
    }

    #[test]
    fn reply_lines_in_any_order_but_complete() {
        let mut s = stage(vec![b"3=3 \n1=1 \n2=2\n", b"1=1 \n2=2\n"]);
        assert_eq!(s.position().unwrap(), [1.0, 2.0, 3.0]);
        match s.position() {
            Err(DeviceError::Garbled { reply, command, .. }) => {
                assert_eq!(command, "POS? 1 2 3");
                assert_eq!(reply, "1=1\\n2=2");
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn units_scale() {
        let mut s = stage(vec![b"1=0.001 \n2=0.002 \n3=0.003\n"]);
        s.opts.units_per_um = 0.001; // controller in mm
        let p = s.position().unwrap();
        assert!(
            (p[0] - 1.0).abs() < 1e-12 && (p[2] - 3.0).abs() < 1e-12,
            "{p:?}"
        );
    }

    #[test]
    fn controller_error_after_move() {
        let mut s = stage(vec![b"", b"7\n"]);
        match s.move_to([500.0, 0.0, 0.0]) {
            Err(DeviceError::Controller {
                code,
                message,
                command,
                ..
            }) => {
                assert_eq!(code, 7);
                assert_eq!(message, "Position out of limits");
                // only the axis that changes is named
                assert_eq!(command, "MOV 1 500.000000");
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn stop_accepts_code_10() {
        let mut s = stage(vec![b"", b"10\n"]);
        s.stop().unwrap();
    }

    #[test]
    fn non_finite_target_is_not_sent() {
        let script = Scripted::new(connect_replies());
        let log = script.log.clone();
        let mut s = GcsStage::connect(Box::new(script), "mock", opts()).unwrap();
        assert!(matches!(
            s.move_to([f64::NAN, 0.0, 0.0]),
            Err(DeviceError::Other { .. })
        ));
        assert_eq!(
            *log.lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner),
            vec!["*IDN?", "ERR?", "SAI?", "SVO? 1 2 3", "MOV? 1 2 3"]
        );
    }

    #[test]
    fn axes_not_on_the_controller_are_refused_naming_what_sai_answered() {
        let mut replies = connect_replies();
        replies.truncate(3);
        replies.push(b"1 \n2 \n3 \n4\n".to_vec()); // SAI? ALL: a deactivated fourth axis
        let script = Scripted::new(replies);
        let log = script.log.clone();
        let o = GcsOptions {
            axes: axes_xyz(["A", "B", "C"]),
            ..opts()
        };
        let e = GcsStage::connect(Box::new(script), "mock", o)
            .err()
            .expect("refused");
        assert_eq!(
            e.to_string(),
            "PI E-727 on mock: configured axes x = \"A\", y = \"B\", z = \"C\" are not all axes of this \
             controller: `SAI?` answered 1 2 3 (`SAI? ALL`, deactivated axes too: 1 2 3 4); A, B, C \
             missing. Set [stage] axes in bfpscope.toml to the controller's identifiers, e.g. axes = \
             { x = \"1\", y = \"2\", z = \"3\" }"
        );
        // nothing after the check: no SVO?, no SVO
        assert_eq!(
            *log.lock().unwrap(),
            vec!["*IDN?", "ERR?", "SAI?", "SAI? ALL"]
        );
    }

    #[test]
    fn one_axis_per_query_is_detected_from_the_svo_reply() {
        let replies: Vec<Vec<u8>> = vec![
            b"x, E-709, 1, 1\n".to_vec(),
            b"0\n".to_vec(),
            b"1 \n2 \n3\n".to_vec(),
            b"1=0\n".to_vec(), // SVO? 1 2 3 answered for axis 1 only
            b"2=1\n".to_vec(),
            b"3=0\n".to_vec(),
            b"1=1.0\n".to_vec(), // MOV? 1
            b"2=2.0\n".to_vec(),
            b"3=3.0\n".to_vec(),
            b"1=4.5\n".to_vec(), // POS? 1
            b"2=5.5\n".to_vec(),
            b"3=6.5\n".to_vec(),
        ];
        let script = Scripted::new(replies);
        let log = script.log.clone();
        let mut s = GcsStage::connect(Box::new(script), "mock", opts()).unwrap();
        assert!(s.one_axis_per_query());
        assert_eq!(s.servo_at_connect(), [Some(false), Some(true), Some(false)]);
        assert_eq!(s.commanded_target().unwrap(), [1.0, 2.0, 3.0]);
        assert_eq!(s.position().unwrap(), [4.5, 5.5, 6.5]);
        assert_eq!(
            log.lock().unwrap()[3..],
            [
                "SVO? 1 2 3",
                "SVO? 2",
                "SVO? 3",
                "MOV? 1",
                "MOV? 2",
                "MOV? 3",
                "POS? 1",
                "POS? 2",
                "POS? 3"
            ]
        );
    }

    #[test]
    fn enable_switches_on_only_the_axes_found_off() {
        let mut replies = connect_replies();
        replies[3] = b"1=1 \n2=0 \n3=0\n".to_vec();
        replies.push(b"".to_vec()); // SVO
        replies.push(b"0\n".to_vec()); // ERR?
        let script = Scripted::new(replies);
        let log = script.log.clone();
        let o = GcsOptions {
            servo_on_connect: true,
            ..opts()
        };
        let _s = GcsStage::connect(Box::new(script), "mock", o).unwrap();
        assert_eq!(log.lock().unwrap()[5..], ["SVO 2 1 3 1", "ERR?"]);
    }

    #[test]
    fn error_texts() {
        assert_eq!(gcs_error_text(1), "Parameter syntax error");
        assert_eq!(gcs_error_text(2), "Unknown command");
        assert!(gcs_error_text(5).contains("servo off"));
        assert_eq!(gcs_error_text(10), "Controller was stopped by command");
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]
        /// Any bytes as a reply: a value, `Garbled` or `Timeout`/`Controller`, never a panic.
        #[test]
        fn garbage_never_panics(reply in proptest::collection::vec(any::<u8>(), 0..200)) {
            let mut s = stage(vec![&reply, b"0\n"]);
            match s.position() {
                Ok(p) => prop_assert!(p.iter().all(|v| v.is_finite())),
                Err(DeviceError::Garbled { .. }) | Err(DeviceError::Timeout { .. })
                | Err(DeviceError::Controller { .. }) => {}
                Err(e) => prop_assert!(false, "unexpected {e:?}"),
            }
        }
    }
}
