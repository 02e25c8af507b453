//! Driver for piezo stage controllers speaking PI's GCS 2.0 ASCII command set (E-727, E-709,
//! E-712, E-517, C-413 …) over RS-232 / USB-serial.
//!
//! The subset used (see `docs/hardware.md`):
//!
//! | command            | reply                      | use                                   |
//! |--------------------|----------------------------|---------------------------------------|
//! | `*IDN?`            | one line                   | identify at connect                   |
//! | `ERR?`             | error code (`0` = none)    | after every command; clears the error |
//! | `SVO A 1 B 1 C 1`  | —                          | closed-loop servo on at connect       |
//! | `MOV A x B y C z`  | —                          | absolute move (controller units)      |
//! | `ONT? A B C`       | `A=1 ␠\nB=1 ␠\nC=0\n`      | poll until every axis is on target    |
//! | `POS? A B C`       | `A=12.3456 ␠\nB=… ␠\nC=…\n` | position                              |
//! | `TMN? A B C` / `TMX? A B C` | as `POS?`         | travel range                          |
//! | `STP`              | — (sets error 10)          | stop all axes                         |
//!
//! Lines end with LF. A multi-line reply marks every line but the last with a space before the
//! LF ("space before LF means more lines follow").
//!
//! The driver only moves and reads: it does not check soft limits (that is `acquire/`'s
//! pre-flight), and a target outside the controller's travel comes back as the controller's
//! own error 7, "Position out of limits".

use super::link::{open_serial, LineLink, Transport};
use super::{DeviceError, Pos, Stage};
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
        -1024 => "Motion error: position error too large, servo is switched off automatically",
        _ => "see the controller manual's error list",
    }
}

/// Most lines a multi-line reply may have before it is treated as garbage.
const MAX_REPLY_LINES: usize = 64;

/// Driver settings (see `[stage]` in `bfpscope.toml`).
#[derive(Debug, Clone, PartialEq)]
pub struct GcsOptions {
    /// Controller axis identifiers for x, y, z (`["A","B","C"]`, `["1","2","3"]`, …).
    pub axes: [String; 3],
    /// Reply timeout for one command.
    pub timeout: Duration,
    /// Longest wait for `ONT?` to report every axis on target after a move.
    pub on_target_timeout: Duration,
    /// Interval between `ONT?` polls.
    pub poll_interval: Duration,
    /// Switch closed-loop servo on for the three axes at connect (`SVO`).
    pub servo_on_connect: bool,
    /// Controller position units per µm (1 for PI piezo controllers, which work in µm;
    /// 0.001 for a controller configured in mm).
    pub units_per_um: f64,
}

impl Default for GcsOptions {
    fn default() -> Self {
        Self {
            axes: ["A".into(), "B".into(), "C".into()],
            timeout: Duration::from_millis(1000),
            on_target_timeout: Duration::from_millis(5000),
            poll_interval: Duration::from_millis(5),
            servo_on_connect: true,
            units_per_um: 1.0,
        }
    }
}

/// A three-axis PI GCS 2.0 stage.
pub struct GcsStage {
    link: LineLink,
    opts: GcsOptions,
    idn: String,
    /// The last commanded target (µm) as sent, per axis: read with `MOV?` when unknown (at the
    /// first move, after a stop), then kept. PI defines relative moves (`MVR`) on the target,
    /// not on the measured position; untouched axes are never re-commanded.
    commanded: Option<Pos>,
}

/// `ONT?` polls between two `ERR?` while waiting for a move to end.
pub const ERR_POLL_EVERY: usize = 10;

impl GcsStage {
    /// Open a serial port (e.g. `/dev/ttyUSB0`, or an emulator's `/dev/pts/N`) and connect.
    pub fn open(port: &str, baud: u32, opts: GcsOptions) -> Result<Self, DeviceError> {
        let device = format!("GCS stage on {port}");
        let io = open_serial(&device, port, baud, opts.timeout)?;
        Self::connect(io, port, opts)
    }

    /// Connect over any transport: identify (`*IDN?`), clear a pending error (`ERR?`), and
    /// switch the servos on if configured. `port` only labels messages.
    pub fn connect(
        io: Box<dyn Transport>,
        port: &str,
        opts: GcsOptions,
    ) -> Result<Self, DeviceError> {
        let link = LineLink::new(io, format!("GCS stage on {port}"), opts.timeout);
        let mut s = Self {
            link,
            opts,
            idn: String::new(),
            commanded: None,
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
        // The targets in force: relative moves start from them, untouched axes keep them.
        s.commanded_target()?;
        if s.opts.servo_on_connect {
            s.set_servo(true)?;
        }
        Ok(s)
    }

    /// The controller's `*IDN?` reply.
    pub fn idn(&self) -> &str {
        &self.idn
    }

    pub fn options(&self) -> &GcsOptions {
        &self.opts
    }

    fn check_axes(&self) -> Result<(), DeviceError> {
        let a = &self.opts.axes;
        let bad = a
            .iter()
            .any(|n| n.is_empty() || n.contains(char::is_whitespace) || n.contains('='))
            || a[0] == a[1]
            || a[0] == a[2]
            || a[1] == a[2];
        if bad {
            return Err(DeviceError::Other {
                device: self.link.device().to_string(),
                detail: format!(
                    "invalid axis map {a:?}: need three distinct identifiers without spaces"
                ),
            });
        }
        Ok(())
    }

    fn axes_list(&self) -> String {
        self.opts.axes.join(" ")
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
        self.link.discard_input();
        self.link.send(command)?;
        let mut lines = Vec::new();
        loop {
            let line = match self.link.read_line(command, self.opts.timeout) {
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
            if lines.len() >= MAX_REPLY_LINES {
                return Err(self.link.garbled(command, lines.join("\\n")));
            }
        }
    }

    /// Query `CMD? A B C` and parse `A=value` lines into x, y, z order.
    fn query_axes<T>(
        &mut self,
        command: &str,
        parse: impl Fn(&str) -> Option<T>,
    ) -> Result<[T; 3], DeviceError> {
        let cmd = format!("{command} {}", self.axes_list());
        let lines = self.query_lines(&cmd)?;
        let mut out: [Option<T>; 3] = [None, None, None];
        let whole = || lines.join("\\n");
        for line in &lines {
            let (key, value) = line
                .split_once('=')
                .ok_or_else(|| self.link.garbled(&cmd, whole()))?;
            let i = self
                .opts
                .axes
                .iter()
                .position(|a| a == key.trim())
                .ok_or_else(|| self.link.garbled(&cmd, whole()))?;
            let v = parse(value.trim()).ok_or_else(|| self.link.garbled(&cmd, whole()))?;
            if out[i].is_some() {
                return Err(self.link.garbled(&cmd, whole()));
            }
            out[i] = Some(v);
        }
        match out {
            [Some(x), Some(y), Some(z)] => Ok([x, y, z]),
            _ => Err(self.link.garbled(&cmd, whole())),
        }
    }

    fn query_positions(&mut self, command: &str) -> Result<Pos, DeviceError> {
        let k = self.opts.units_per_um;
        let v = self.query_axes(command, |s| s.parse::<f64>().ok().filter(|v| v.is_finite()))?;
        Ok([v[0] / k, v[1] / k, v[2] / k])
    }

    /// `ONT? A B C`: on-target state of x, y, z.
    pub fn on_target(&mut self) -> Result<[bool; 3], DeviceError> {
        self.query_axes("ONT?", |s| match s {
            "1" => Some(true),
            "0" => Some(false),
            _ => None,
        })
    }

    /// Poll `ONT?` until every axis is on target, at most `on_target_timeout` after `after`.
    pub fn wait_on_target(&mut self, after: &str) -> Result<(), DeviceError> {
        let t0 = Instant::now();
        let mut polls = 0usize;
        loop {
            let ont = self.on_target()?;
            if ont.iter().all(|&b| b) {
                return Ok(());
            }
            polls += 1;
            let timed_out = t0.elapsed() >= self.opts.on_target_timeout;
            // Asynchronous errors (e.g. −1024, the servo tripped) surface only in ERR?: read it
            // every ERR_POLL_EVERY polls and when the wait ends badly, so a servo trip is
            // reported as itself, not as "not on target".
            if timed_out || polls.is_multiple_of(ERR_POLL_EVERY) {
                let code = self.error_code(after)?;
                if code != 0 {
                    return Err(self.controller_error(after, code));
                }
            }
            if timed_out {
                let state: Vec<String> = self
                    .opts
                    .axes
                    .iter()
                    .zip(ont)
                    .map(|(a, b)| format!("{a}={}", u8::from(b)))
                    .collect();
                return Err(DeviceError::Other {
                    device: self.link.device().to_string(),
                    detail: format!(
                        "not on target within {} ms after `{after}` (last `ONT? {}` reply: {})",
                        self.opts.on_target_timeout.as_millis(),
                        self.axes_list(),
                        state.join(" ")
                    ),
                });
            }
            std::thread::sleep(self.opts.poll_interval);
        }
    }

    /// `SVO A s B s C s`.
    pub fn set_servo(&mut self, on: bool) -> Result<(), DeviceError> {
        let s = u8::from(on);
        let cmd = self
            .opts
            .axes
            .iter()
            .map(|a| format!("{a} {s}"))
            .collect::<Vec<_>>()
            .join(" ");
        self.command(&format!("SVO {cmd}"))
    }

    /// The last commanded target (µm): `MOV?` when not known yet, then what was sent.
    pub fn commanded_target(&mut self) -> Result<Pos, DeviceError> {
        match self.commanded {
            Some(t) => Ok(t),
            None => {
                let t = self.query_positions("MOV?")?;
                self.commanded = Some(t);
                Ok(t)
            }
        }
    }

    /// `MOV` for the axes whose target changes, without waiting (positions in µm). An axis
    /// whose target, as sent (6 decimals of controller units), equals its last commanded target
    /// is not named, so the targets of untouched axes never wander. Returns the command sent,
    /// or `None` when no axis changes.
    pub fn move_no_wait(&mut self, target: Pos) -> Result<Option<String>, DeviceError> {
        if target.iter().any(|v| !v.is_finite()) {
            return Err(DeviceError::Other {
                device: self.link.device().to_string(),
                detail: format!("refusing to send a non-finite target {target:?} µm"),
            });
        }
        let now = self.commanded_target()?;
        let k = self.opts.units_per_um;
        let sent = |v: f64| format!("{:.6}", v * k);
        // (axis, value as sent) for the axes whose target changes
        let changed: Vec<(usize, String)> = (0..3)
            .map(|i| (i, sent(target[i])))
            .filter(|(i, v)| *v != sent(now[*i]))
            .collect();
        if changed.is_empty() {
            return Ok(None);
        }
        let parts: Vec<String> = changed
            .iter()
            .map(|(i, v)| format!("{} {v}", self.opts.axes[*i]))
            .collect();
        let cmd = format!("MOV {}", parts.join(" "));
        // unknown until the controller has accepted it (an error leaves the old targets)
        self.commanded = None;
        self.command(&cmd)?;
        let mut t = now;
        for (i, v) in &changed {
            t[*i] = v.parse::<f64>().unwrap_or(target[*i] * k) / k;
        }
        self.commanded = Some(t);
        Ok(Some(cmd))
    }
}

impl Stage for GcsStage {
    fn name(&self) -> String {
        self.link.device().to_string()
    }

    fn position(&mut self) -> Result<Pos, DeviceError> {
        self.query_positions("POS?")
    }

    fn target(&mut self) -> Result<Pos, DeviceError> {
        self.commanded_target()
    }

    /// `VEL A v B v C v` (controller units per s), then `ERR?`.
    fn set_velocity(&mut self, um_s: f64) -> Result<(), DeviceError> {
        if !(um_s.is_finite() && um_s > 0.0) {
            return Err(DeviceError::Other {
                device: self.name(),
                detail: format!("refusing to send a velocity of {um_s} µm/s"),
            });
        }
        let v = format!("{:.6}", um_s * self.opts.units_per_um);
        let cmd = format!(
            "VEL {}",
            self.opts
                .axes
                .iter()
                .map(|a| format!("{a} {v}"))
                .collect::<Vec<_>>()
                .join(" ")
        );
        self.command(&cmd)
    }

    fn velocity(&mut self) -> Result<Option<Pos>, DeviceError> {
        self.query_positions("VEL?").map(Some)
    }

    /// A GCS query: a command word ending in `?` with its arguments (`SAI?`, `POS? 1`, `*IDN?`,
    /// `VEL?`). Everything else is refused before anything is sent: motion goes through the
    /// engine.
    fn raw_query(&mut self, query: &str) -> Result<Vec<String>, DeviceError> {
        let q = query.trim();
        let word = q.split_whitespace().next().unwrap_or("");
        let safe_chars = q
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || " ?*._-".contains(c));
        if !(word.ends_with('?') && safe_chars) {
            return Err(DeviceError::Other {
                device: self.name(),
                detail: format!(
                    "`{q}` is not a query: only GCS queries (a command ending in `?`) are sent from the prompt; moves go through mv, mvr and the scans"
                ),
            });
        }
        self.query_lines(q)
    }

    fn move_to(&mut self, target: Pos) -> Result<(), DeviceError> {
        match self.move_no_wait(target)? {
            Some(cmd) => self.wait_on_target(&cmd),
            None => Ok(()),
        }
    }

    fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError> {
        let lo = self.query_positions("TMN?")?;
        let hi = self.query_positions("TMX?")?;
        Ok([(lo[0], hi[0]), (lo[1], hi[1]), (lo[2], hi[2])])
    }

    /// `STP`, then `ERR?`: error 10 ("stopped by command") is the expected answer and is
    /// cleared; any other nonzero code is reported.
    fn stop(&mut self) -> Result<(), DeviceError> {
        // where the axes stop is where the controller says their targets are now
        self.commanded = None;
        self.link.discard_input();
        self.link.send("STP")?;
        match self.error_code("STP")? {
            0 | 10 => Ok(()),
            code => Err(self.controller_error("STP", code)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::link::mock::Scripted;
    use super::*;
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

    fn stage(replies: Vec<&[u8]>) -> GcsStage {
        let mut all: Vec<Vec<u8>> = vec![
            b"(c)2026 Physik Instrumente (PI) GmbH & Co. KG, E-727, 1, 1\n".to_vec(),
            b"0\n".to_vec(),
            b"A=0.000000 \nB=0.000000 \nC=0.000000\n".to_vec(),
        ];
        all.extend(replies.into_iter().map(|r| r.to_vec()));
        GcsStage::connect(Box::new(Scripted::new(all)), "mock", opts()).unwrap()
    }

    #[test]
    fn multi_line_reply_and_name() {
        let mut s = stage(vec![b"A=1.5 \nB=-2.25 \nC=10\n"]);
        assert_eq!(s.name(), "PI E-727 on mock");
        assert_eq!(s.position().unwrap(), [1.5, -2.25, 10.0]);
    }

    #[test]
    fn reply_lines_in_any_order_but_complete() {
        let mut s = stage(vec![b"C=3 \nA=1 \nB=2\n", b"A=1 \nB=2\n"]);
        assert_eq!(s.position().unwrap(), [1.0, 2.0, 3.0]);
        match s.position() {
            Err(DeviceError::Garbled { reply, command, .. }) => {
                assert_eq!(command, "POS? A B C");
                assert_eq!(reply, "A=1\\nB=2");
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn units_scale() {
        let mut s = stage(vec![b"A=0.001 \nB=0.002 \nC=0.003\n"]);
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
                assert_eq!(command, "MOV A 500.000000");
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
        let script = Scripted::new(vec![
            b"x, E-727, 1, 1\n".to_vec(),
            b"0\n".to_vec(),
            b"A=0 \nB=0 \nC=0\n".to_vec(),
        ]);
        let log = script.log.clone();
        let mut s = GcsStage::connect(Box::new(script), "mock", opts()).unwrap();
        assert!(matches!(
            s.move_to([f64::NAN, 0.0, 0.0]),
            Err(DeviceError::Other { .. })
        ));
        assert_eq!(
            *log.lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner),
            vec!["*IDN?", "ERR?", "MOV? A B C"]
        );
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
