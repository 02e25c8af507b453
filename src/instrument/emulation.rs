//! What every device emulator shares: serving a device's command lines on a pseudo-terminal
//! or a TCP port ([`Emulator`]), the shared stage position and wave path, fault injection and
//! the link model. The emulators themselves live with their family (`gcs/emulator.rs`,
//! `scpi/emulator.rs`, `redpitaya/emulator.rs`, `thorlabs/emulator.rs`); `emulator/` starts
//! them together for `connect(#{backend: "emulated"})` and `bfpscope emulate`.
//!
//! Each emulator runs on its own thread and serves the master side of a PTY pair
//! (`serialport::TTYPort::pair()`); a driver opens the slave path ([`Emulator::path`], e.g.
//! `/dev/pts/7`) exactly as it would open `/dev/ttyUSB0`. The stage and QPD emulators share the
//! stage position ([`SharedPosition`]), so the QPD answers with the signal of a
//! [`SignalSource`] at the emulated stage's current position and a scan through the real
//! drivers images the emulated scene.
//!
//! Faults are switched at run time through [`Emulator::faults`]: go silent, garble replies,
//! an error code on the next command, unplug after N commands, slow settling, accept
//! out-of-range targets. Every thread stops on its stop flag (set by [`Emulator::stop`] and on
//! drop) or when it unplugs itself.

use super::Pos;
use serialport::TTYPort;
use std::collections::VecDeque;
use std::io::{Read, Write};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// The emulated stage position (µm) shared by the stage and QPD emulators.
pub type SharedPosition = Arc<Mutex<Pos>>;

/// A new shared position at `p`.
pub fn shared_position(p: Pos) -> SharedPosition {
    Arc::new(Mutex::new(p))
}

/// The path of the axes a running wave generator drives, published by the GCS stage emulator
/// at `WGO` for the digitiser emulators that sample the stage during a whole acquisition (the
/// Red Pitaya's triggered buffer): the start instant (servo cycle 0 = the generator's first
/// cycle, when its trigger output fires), the servo cycle and the position of each driven
/// axis after every cycle, computed at `WGO` from the wave table and the lag model as the
/// servo loop computes it (deterministic), truncated at `WGO g 0`, `STP`, `HLT` (the axes hold
/// where they stopped) and cleared by the next `MOV`. Clone it into both emulators.
#[derive(Debug, Clone, Default)]
pub struct StagePath(Arc<Mutex<Option<PathData>>>);

/// Two handles are equal when they are the same path.
impl PartialEq for StagePath {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

/// One published path (see [`StagePath`]).
#[derive(Debug, Clone, PartialEq)]
pub struct PathData {
    /// Instant of servo cycle 0.
    pub start: std::time::Instant,
    /// Servo cycle, s.
    pub dt: f64,
    /// Position of every axis when the generator started, µm.
    pub base: Pos,
    /// Per axis: the position after servo cycle k (`None`: the axis is not driven).
    pub x: [Option<Vec<f64>>; 3],
    /// The cycle at which the generator was stopped, if it was.
    pub stop: Option<usize>,
}

impl PathData {
    /// Stage position at servo cycle `k` (µm).
    pub fn at_cycle(&self, k: usize) -> Pos {
        let mut p = self.base;
        for (i, x) in self.x.iter().enumerate() {
            if let Some(x) = x {
                if let Some(last) = x.len().checked_sub(1) {
                    p[i] = x[k.min(self.stop.unwrap_or(last)).min(last)];
                }
            }
        }
        p
    }

    /// Stage position `s` seconds after servo cycle 0 (µm): the positions after cycles k and
    /// k + 1 are the sensor's samples of a continuous motion at `k·dt` and `(k+1)·dt`
    /// (what the data recorder records at those cycles), linear in between, as the raster
    /// engine interpolates the record. (Holding the position of cycle k over the whole cycle
    /// would lag the stage by half a servo cycle: 1.25 nm at 50 µm/s and 50 µs, opposite in
    /// a snake raster's two directions.) Before the start: cycle 0.
    pub fn at_time(&self, s: f64) -> Pos {
        let u = (s / self.dt).max(0.0);
        let k = u.floor() as usize;
        let f = u - k as f64;
        let (a, b) = (self.at_cycle(k), self.at_cycle(k + 1));
        std::array::from_fn(|i| a[i] + f * (b[i] - a[i]))
    }
}

impl StagePath {
    pub fn new() -> Self {
        Self::default()
    }
    /// Publish a new path (at `WGO`).
    pub fn set(&self, p: PathData) {
        *lock(&self.0) = Some(p);
    }
    /// The generator stopped at servo cycle `k` after the start: the axes hold from then on.
    pub fn truncate(&self, k: usize) {
        if let Some(p) = lock(&self.0).as_mut() {
            p.stop = Some(p.stop.map_or(k, |s| s.min(k)));
        }
    }
    /// No path any more (a `MOV` took over the axes).
    pub fn clear(&self) {
        *lock(&self.0) = None;
    }
    /// A copy of the path in force.
    pub fn get(&self) -> Option<PathData> {
        lock(&self.0).clone()
    }
    /// Stage position at instant `t` (µm): between the positions of the servo cycles around
    /// it ([`PathData::at_time`]); the start position before the start; `None` without a path.
    pub fn position_at(&self, t: std::time::Instant) -> Option<Pos> {
        let g = lock(&self.0);
        let p = g.as_ref()?;
        if t < p.start {
            return Some(p.base);
        }
        Some(p.at_time((t - p.start).as_secs_f64()))
    }
}

/// A digitiser's external trigger input (the Red Pitaya's DIO0_P on extension connector E1),
/// wired to a stage controller's trigger output (the GCS emulator's `CTO` lines): each [`pulse`](Self::pulse)
/// is one rising and one falling edge. Clone it into whatever emulates the controller's
/// trigger output.
///
/// A pulse carries the instant its rising edge happened (the controller emulator computes its
/// servo loop lazily, so it may register the pulse a few ms after its edge): the board dates
/// its trigger by that instant.
#[derive(Debug, Clone, Default)]
pub struct ExtTrigger(Arc<(AtomicU64, Mutex<Option<Instant>>)>);

/// Two handles are equal when they are the same wire.
impl PartialEq for ExtTrigger {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

impl ExtTrigger {
    pub fn new() -> Self {
        Self::default()
    }
    /// One trigger pulse, now.
    pub fn pulse(&self) {
        self.pulse_at(Instant::now());
    }
    /// One trigger pulse whose rising edge was at `at`.
    pub fn pulse_at(&self, at: Instant) {
        *lock(&self.0 .1) = Some(at);
        self.0 .0.fetch_add(1, Ordering::SeqCst);
    }
    /// Pulses so far.
    pub fn count(&self) -> u64 {
        self.0 .0.load(Ordering::SeqCst)
    }
    /// The instant of the last pulse's rising edge.
    pub fn last_edge(&self) -> Option<Instant> {
        *lock(&self.0 .1)
    }
}

/// Where the QPD emulator's signal comes from: stage position (µm) → (Sx, Sy, Sz) in
/// workbench signal units. Plug the simulator in here; tests use [`standin_bead`].
pub trait SignalSource: Fn(Pos) -> [f64; 3] + Send + 'static {}
impl<F: Fn(Pos) -> [f64; 3] + Send + 'static> SignalSource for F {}

/// A simple analytic stand-in for a bead at the origin (not physics; it proves the plumbing):
/// with `g = exp(−(x²+y²)/0.16 − z²/0.5)`: Sx = x·g, Sy = y·g, Sz = 0.2·g (x, y, z in µm).
pub fn standin_bead(p: Pos) -> [f64; 3] {
    let [x, y, z] = p;
    let g = (-(x * x + y * y) / 0.16 - z * z / 0.5).exp();
    [x * g, y * g, 0.2 * g]
}

/// Fault-injection switches. Change them at run time with [`Emulator::faults`].
#[derive(Debug, Clone, PartialEq)]
pub struct Faults {
    /// Read commands but never answer (a hung controller, a cable with only TX connected).
    pub silent: bool,
    /// Garble the next N replies: a 0xFF byte, then the reply with every digit replaced by
    /// `#`. (Replies only: commands without a reply are not affected.)
    pub garble_replies: usize,
    /// Reject the next command (other than the error query itself) with this error code: the
    /// command is not executed, a query gets no reply, and the error query returns the code.
    pub error_next: Option<i64>,
    /// `Some((n, code))`: serve n more commands normally, then reject the next command (other
    /// than the error query) with `code`, as `error_next` does. Deterministic mid-sequence
    /// errors (the 3rd `MOV` of a scan, …).
    pub error_after: Option<(usize, i64)>,
    /// Serve this many more commands, then close the port (unplugged cable, power loss). The
    /// last reply is sent 50 ms before the line goes dead; commands sent meanwhile are lost.
    pub unplug_after: Option<usize>,
    /// Stage: time to settle on a new target in s, overriding the configured settle time
    /// (slow settling).
    pub settle_s: Option<f64>,
    /// PI stage: settling time in s (E-727 parameter 0x07000901), overriding the configured
    /// one: after the trajectory has ended (`#5` answers 0) `ONT?` stays 0 until the axis has
    /// been inside the settling window this long (a slowly settling, or ringing, axis).
    pub settling_time_s: Option<f64>,
    /// Stage: reject targets outside the travel range with error 7, as real controllers do.
    /// When false the target is silently clamped to the travel range.
    pub reject_out_of_range: bool,
    /// Stage: sensor noise of `POS?` replies, µm (uniform, ± this value; deterministic). A
    /// closed-loop piezo reads its capacitive sensor with nanometre noise around the target;
    /// `MOV?` answers the target itself.
    pub pos_noise_um: f64,
    /// Stage: the next `MOV` is accepted, then the servo of its axes trips as a real E-727's
    /// does when the position error grows too large: the axes stop where they are, servo off,
    /// never on target, and the error register holds −1024 (read by the next `ERR?`).
    pub servo_trip_next_move: bool,
    /// APT emulators: send a message with an unknown id (`UNKNOWN_ID`) before each of the
    /// next n replies (the driver must skip it).
    pub apt_unsolicited: usize,
    /// APT emulators: serve n more messages, then go silent (a device that stops answering
    /// at a chosen point of a scan).
    pub silent_after: Option<usize>,
    /// `Some(n)`: serve n more commands normally, then garble the reply to the next one (as
    /// `garble_replies = 1` then): a garbled reply at a chosen point of a scan.
    pub garble_after: Option<usize>,
    /// Text emulators: end every reply line with CR LF instead of LF (controllers and
    /// USB–serial bridges that do; the driver must read the same values).
    pub crlf: bool,
    /// Digitisers (Red Pitaya): no trigger ever fires (a trigger cable not connected, a
    /// controller that never sends its trigger); `ACQ:TRIG:STAT?` stays `WAIT`.
    pub no_trigger: bool,
    /// Text emulators: `Some((word, n, code))`: serve n more commands whose first word is
    /// `word` (case-insensitive, e.g. `"DRR?"`) normally, then reject the next one with `code`
    /// as `error_next` does (a query gets no reply; the error query returns the code). A
    /// chosen command failing at a chosen point of a scan (the 3rd line's `DRR?`).
    pub reject: Option<(String, usize, i64)>,
}

impl Default for Faults {
    fn default() -> Self {
        Self {
            silent: false,
            garble_replies: 0,
            error_next: None,
            error_after: None,
            unplug_after: None,
            settle_s: None,
            settling_time_s: None,
            reject_out_of_range: true,
            pos_noise_um: 0.0,
            servo_trip_next_move: false,
            apt_unsolicited: 0,
            silent_after: None,
            garble_after: None,
            crlf: false,
            no_trigger: false,
            reject: None,
        }
    }
}

/// Garbled form of a reply (see [`Faults::garble_replies`]).
pub fn garble(reply: &str) -> Vec<u8> {
    let mut out = vec![0xFF];
    out.extend(
        reply
            .bytes()
            .map(|b| if b.is_ascii_digit() { b'#' } else { b }),
    );
    out
}

/// The serial link an emulator models (a USB-serial PI controller, a digitiser on a serial
/// line): each byte takes 10 bit times (8N1: start, 8 data, stop) at `baud`, both ways, and a
/// reply starts `latency` after the command has arrived (the device's processing plus the
/// USB-serial bridge's buffering). `baud: None` and zero latency: the pseudo-terminal's full
/// speed (what the tests use).
///
/// The emulator's thread is the wire: while a command's bytes arrive and while a reply goes
/// out it serves nothing else, as a controller with one serial port does.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkModel {
    /// Bits per second; `None`: no limit (the pseudo-terminal's own speed).
    pub baud: Option<u32>,
    /// Time from the end of a command to the start of its reply.
    pub latency: Duration,
}

impl LinkModel {
    /// The pseudo-terminal's full speed: no baud limit, no latency.
    pub const FULL_SPEED: LinkModel = LinkModel {
        baud: None,
        latency: Duration::ZERO,
    };
    /// A USB-serial PI controller (E-727, E-709, C-867) at its default 115200 baud with 1 ms
    /// reply latency: `bfpscope emulate`'s default.
    pub const USB_SERIAL_115200: LinkModel = LinkModel {
        baud: Some(115_200),
        latency: Duration::from_millis(1),
    };

    /// Seconds `bytes` take on the wire: `bytes · 10 / baud` (0 at full speed).
    pub fn wire_s(&self, bytes: usize) -> f64 {
        match self.baud {
            Some(b) if b > 0 => bytes as f64 * 10.0 / b as f64,
            _ => 0.0,
        }
    }

    /// `115200 baud, 1 ms latency` or `full speed`.
    pub fn describe(&self) -> String {
        match self.baud {
            None if self.latency.is_zero() => "pseudo-terminal full speed".into(),
            None => format!(
                "no baud limit, {} ms latency",
                self.latency.as_secs_f64() * 1e3
            ),
            Some(b) => format!("{b} baud, {} ms latency", self.latency.as_secs_f64() * 1e3),
        }
    }
}

impl Default for LinkModel {
    /// [`LinkModel::FULL_SPEED`] (the Rust configs, used by the tests);
    /// `bfpscope emulate` uses [`LinkModel::USB_SERIAL_115200`].
    fn default() -> Self {
        Self::FULL_SPEED
    }
}

pub(crate) fn sleep_s(s: f64) {
    if s > 0.0 && s.is_finite() {
        std::thread::sleep(Duration::from_secs_f64(s));
    }
}

/// Most commands kept in an emulator's command log.
pub(crate) const LOG_CAP: usize = 100_000;

/// A running emulator. Dropping it stops the thread and closes the port.
pub struct Emulator {
    path: String,
    kind: &'static str,
    faults: Arc<Mutex<Faults>>,
    log: Arc<Mutex<VecDeque<String>>>,
    stop: Arc<AtomicBool>,
    finished: Arc<AtomicBool>,
    position: SharedPosition,
    thread: Option<JoinHandle<()>>,
}

pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Emulator {
    /// The pseudo-terminal path a driver opens (`/dev/pts/N`).
    pub fn path(&self) -> &str {
        &self.path
    }

    /// `"stage"` or `"qpd"`.
    pub fn kind(&self) -> &'static str {
        self.kind
    }

    /// The fault switches (hold the guard briefly: the emulator thread waits on it).
    pub fn faults(&self) -> MutexGuard<'_, Faults> {
        lock(&self.faults)
    }

    /// The fault switches as a shared handle (for a thread that flips one when something
    /// happens).
    pub fn faults_handle(&self) -> Arc<Mutex<Faults>> {
        self.faults.clone()
    }

    /// Every command line received so far (oldest first; the last 100 000).
    pub fn commands(&self) -> Vec<String> {
        lock(&self.log).iter().cloned().collect()
    }

    /// A reader of the command log that outlives this borrow (for a watcher thread that acts
    /// when a command arrives): each call returns [`commands`](Self::commands) as of then.
    pub fn command_log(&self) -> impl Fn() -> Vec<String> + Send + 'static {
        let log = self.log.clone();
        move || lock(&log).iter().cloned().collect()
    }

    /// The shared emulated stage position (µm).
    pub fn position(&self) -> Pos {
        *lock(&self.position)
    }

    pub fn shared_position(&self) -> SharedPosition {
        self.position.clone()
    }

    /// False once the thread has ended (stopped or unplugged).
    pub fn is_running(&self) -> bool {
        !self.finished.load(Ordering::SeqCst)
    }

    /// Stop serving and close the port; returns when the thread has ended.
    pub fn stop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for Emulator {
    fn drop(&mut self) {
        self.stop();
    }
}

/// What an emulated device does with one command line.
pub(crate) trait Device: Send + 'static {
    /// Handle one command; `Some(reply)` (without the final LF) if it answers.
    fn handle(&mut self, line: &str) -> Option<String>;
    /// Record a device error code (fault injection).
    fn inject_error(&mut self, code: i64);
    /// True for the error query (`ERR?`, `SYST:ERR?`), which injected errors do not hit.
    fn is_error_query(&self, line: &str) -> bool;
    /// Called about every 5 ms and before each command: advance dynamics.
    fn tick(&mut self) {}
    /// A single-character command this device answers at once, without a line end (PI GCS:
    /// `#5` = 0x05, `#7` = 0x07, `#24` = 0x18): its name (`"#5"`), handled as that line.
    fn single_char(&self, _byte: u8) -> Option<&'static str> {
        None
    }
}

/// Where an emulator serves: the master side of a pseudo-terminal, or a TCP listener serving
/// one client at a time (a PI controller's GCS port).
pub(crate) enum Line {
    Pty {
        master: TTYPort,
        // Holding the slave open keeps the pseudo-terminal alive between client sessions
        // (a master whose slave is closed by everyone reports hang-up).
        _slave: TTYPort,
    },
    Tcp {
        listener: std::net::TcpListener,
        client: Option<std::net::TcpStream>,
    },
}

impl Line {
    /// Read what arrived within about 5 ms: `Ok(0)` when nothing did (or no client is
    /// connected yet), `Err(TimedOut)` on a timeout. A new TCP client starts a new session
    /// (`new_session` is set: drop partial input).
    pub(crate) fn read(
        &mut self,
        buf: &mut [u8],
        new_session: &mut bool,
    ) -> std::io::Result<usize> {
        match self {
            Line::Pty { master, .. } => master.read(buf),
            Line::Tcp { listener, client } => {
                let Some(c) = client else {
                    match listener.accept() {
                        Ok((stream, _)) => {
                            stream.set_nonblocking(false)?;
                            stream.set_read_timeout(Some(Duration::from_millis(5)))?;
                            let _ = stream.set_nodelay(true);
                            *client = Some(stream);
                            *new_session = true;
                        }
                        Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
                        Err(e) => return Err(e),
                    }
                    return Ok(0);
                };
                match c.read(buf) {
                    Ok(0) => {
                        // the client closed: wait for the next one
                        *client = None;
                        Ok(0)
                    }
                    Ok(n) => Ok(n),
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => Err(
                        std::io::Error::new(std::io::ErrorKind::TimedOut, "no input"),
                    ),
                    Err(e) if e.kind() == std::io::ErrorKind::TimedOut => Err(e),
                    Err(_) => {
                        *client = None;
                        Ok(0)
                    }
                }
            }
        }
    }

    pub(crate) fn write_all(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        match self {
            Line::Pty { master, .. } => master.write_all(bytes).and_then(|_| master.flush()),
            Line::Tcp { client, .. } => match client {
                Some(c) => c.write_all(bytes).and_then(|_| c.flush()),
                None => Ok(()),
            },
        }
    }
}

/// A pseudo-terminal pair: the master side an emulator serves, and the path clients open.
pub(crate) fn pty_line() -> std::io::Result<(Line, String)> {
    let (mut master, slave) = TTYPort::pair().map_err(std::io::Error::from)?;
    let path = serialport::SerialPort::name(&slave)
        .ok_or_else(|| std::io::Error::other("pseudo-terminal without a name"))?;
    let _ = serialport::SerialPort::set_timeout(&mut master, Duration::from_millis(5));
    Ok((
        Line::Pty {
            master,
            _slave: slave,
        },
        path,
    ))
}

/// A TCP listener on `addr` (e.g. `127.0.0.1:0` for a free port) serving one client at a time,
/// and its path `tcp://IP:PORT`.
pub(crate) fn tcp_line(addr: &str) -> std::io::Result<(Line, String)> {
    let listener = std::net::TcpListener::bind(addr)?;
    listener.set_nonblocking(true)?;
    let path = format!("tcp://{}", listener.local_addr()?);
    Ok((
        Line::Tcp {
            listener,
            client: None,
        },
        path,
    ))
}

/// Serve `device` on `line` ([`pty_line`], [`tcp_line`]) on a new thread; clients open `path`.
pub(crate) fn spawn(
    kind: &'static str,
    device: impl Device,
    faults: Arc<Mutex<Faults>>,
    position: SharedPosition,
    (line, path): (Line, String),
    link: LinkModel,
) -> std::io::Result<Emulator> {
    let f = faults.clone();
    launch(kind, faults, position, path, move |h| {
        Serve {
            line,
            device,
            faults: f,
            link,
            log: h.log,
            stop: h.stop,
            finished: h.finished,
        }
        .run()
    })
}

/// What a serving thread shares with its [`Emulator`] handle.
pub(crate) struct Served {
    pub log: Arc<Mutex<VecDeque<String>>>,
    pub stop: Arc<AtomicBool>,
    pub finished: Arc<AtomicBool>,
}

/// Run `serve` on a new thread named after `kind` and return the handle that shares its log,
/// stop and finished flags (every emulator, text or binary protocol, starts this way).
pub(crate) fn launch(
    kind: &'static str,
    faults: Arc<Mutex<Faults>>,
    position: SharedPosition,
    path: String,
    serve: impl FnOnce(Served) + Send + 'static,
) -> std::io::Result<Emulator> {
    let log = Arc::new(Mutex::new(VecDeque::new()));
    let stop = Arc::new(AtomicBool::new(false));
    let finished = Arc::new(AtomicBool::new(false));
    let shared = Served {
        log: log.clone(),
        stop: stop.clone(),
        finished: finished.clone(),
    };
    let thread = std::thread::Builder::new()
        .name(format!("emulator-{kind}"))
        .spawn(move || serve(shared))?;
    Ok(Emulator {
        path,
        kind,
        faults,
        log,
        stop,
        finished,
        position,
        thread: Some(thread),
    })
}

struct Serve<D: Device> {
    line: Line,
    device: D,
    faults: Arc<Mutex<Faults>>,
    link: LinkModel,
    log: Arc<Mutex<VecDeque<String>>>,
    stop: Arc<AtomicBool>,
    finished: Arc<AtomicBool>,
}

/// Longest command line accepted; longer input is dropped as line noise.
const MAX_COMMAND: usize = 4096;

impl<D: Device> Serve<D> {
    fn run(mut self) {
        let mut buf: Vec<u8> = Vec::new();
        let mut chunk = [0u8; 1024];
        'serve: while !self.stop.load(Ordering::SeqCst) && !self.unplugged() {
            self.device.tick();
            let mut new_session = false;
            let r = self.line.read(&mut chunk, &mut new_session);
            if new_session {
                buf.clear();
            }
            match r {
                Ok(0) => std::thread::sleep(Duration::from_millis(5)),
                Ok(n) => buf.extend_from_slice(&chunk[..n]),
                Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                // No client has the slave open (we hold it, so rare): wait for one.
                Err(_) => std::thread::sleep(Duration::from_millis(5)),
            }
            // in the order received: a line at its LF; a single-character command (PI's #5,
            // #7, #24) at once, even in the middle of a line
            let mut i = 0;
            while i < buf.len() {
                if buf[i] == b'\n' {
                    let raw: Vec<u8> = buf.drain(..=i).collect();
                    i = 0;
                    let line = String::from_utf8_lossy(&raw[..raw.len() - 1])
                        .trim_end_matches('\r')
                        .to_string();
                    if line.trim().is_empty() {
                        continue;
                    }
                    if !self.serve_command(&line, raw.len()) {
                        // Let the last reply reach the client before the line goes dead (a
                        // pseudo-terminal that hangs up with data pending loses that data).
                        std::thread::sleep(Duration::from_millis(50));
                        break 'serve;
                    }
                } else if let Some(name) = self.device.single_char(buf[i]) {
                    buf.remove(i);
                    if !self.serve_command(name, 1) {
                        std::thread::sleep(Duration::from_millis(50));
                        break 'serve;
                    }
                } else {
                    i += 1;
                }
            }
            if buf.len() > MAX_COMMAND {
                buf.clear();
            }
        }
        self.finished.store(true, Ordering::SeqCst);
        // Dropping `self` closes master and slave (or the TCP connection and the listener):
        // the client sees a hang-up.
    }

    /// Serve one command of `wire_bytes` bytes as sent (line end included); false when the
    /// emulator unplugs itself. With a [`LinkModel`] the command's bytes take their time to
    /// arrive before the device acts on it, and a reply starts after the latency and takes its
    /// bytes' time to go out.
    fn serve_command(&mut self, line: &str, wire_bytes: usize) -> bool {
        sleep_s(self.link.wire_s(wire_bytes));
        {
            let mut log = lock(&self.log);
            if log.len() >= LOG_CAP {
                log.pop_front();
            }
            log.push_back(line.to_string());
        }
        self.device.tick();
        let (silent, inject, garble_it, last) = {
            let mut f = lock(&self.faults);
            // counted before the reply goes out: a client that set the switch after reading
            // the previous reply must not find that reply's command counted against it
            let last = match f.unplug_after {
                Some(n) => {
                    f.unplug_after = Some(n.saturating_sub(1));
                    n <= 1
                }
                None => false,
            };
            let is_err_query = self.device.is_error_query(line);
            if let Some((0, code)) = f.error_after {
                if !is_err_query {
                    f.error_after = None;
                    f.error_next = Some(code);
                }
            } else if let Some((n, code)) = f.error_after {
                f.error_after = Some((n - 1, code));
            }
            match f.garble_after {
                Some(0) => {
                    f.garble_after = None;
                    f.garble_replies += 1;
                }
                Some(n) => f.garble_after = Some(n - 1),
                None => {}
            }
            let word = line.split_whitespace().next().unwrap_or("");
            let mut rejected = None;
            if let Some((w, n, code)) = &mut f.reject {
                if w.eq_ignore_ascii_case(word) {
                    if *n == 0 {
                        rejected = Some(*code);
                    } else {
                        *n -= 1;
                    }
                }
            }
            if rejected.is_some() {
                f.reject = None;
            }
            let inject = if rejected.is_some() {
                rejected
            } else if f.error_next.is_some() && !is_err_query {
                f.error_next.take()
            } else {
                None
            };
            (f.silent, inject, f.garble_replies > 0, last)
        };
        let reply = if let Some(code) = inject {
            self.device.inject_error(code);
            None
        } else {
            self.device.handle(line)
        };
        if let (Some(r), false) = (reply, silent) {
            let mut bytes = if garble_it {
                let mut f = lock(&self.faults);
                f.garble_replies = f.garble_replies.saturating_sub(1);
                garble(&r)
            } else {
                // ISO 8859-1: PI's `#7` answers the single byte 0xB1 ("±"); all else is ASCII
                r.chars()
                    .map(|c| u8::try_from(u32::from(c)).unwrap_or(b'?'))
                    .collect()
            };
            bytes.push(b'\n');
            if lock(&self.faults).crlf {
                let mut v = Vec::with_capacity(bytes.len() + 8);
                for b in bytes {
                    if b == b'\n' {
                        v.push(b'\r');
                    }
                    v.push(b);
                }
                bytes = v;
            }
            sleep_s(self.link.latency.as_secs_f64() + self.link.wire_s(bytes.len()));
            if self.line.write_all(&bytes).is_err() {
                // The client went away mid-reply; keep serving for the next one.
            }
        }
        !last
    }

    fn unplugged(&self) -> bool {
        lock(&self.faults).unplug_after == Some(0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn standin_is_odd_in_x_and_peaks_near_0_28() {
        let a = standin_bead([0.2, 0.0, 0.0]);
        let b = standin_bead([-0.2, 0.0, 0.0]);
        assert_eq!(a[0], -b[0]);
        // d/dx x·exp(−x²/0.16) = 0 at x = sqrt(0.08)
        let x0 = 0.08f64.sqrt();
        assert!(standin_bead([x0, 0.0, 0.0])[0] > standin_bead([x0 + 0.01, 0.0, 0.0])[0]);
        assert!(standin_bead([x0, 0.0, 0.0])[0] > standin_bead([x0 - 0.01, 0.0, 0.0])[0]);
        assert_eq!(standin_bead([0.0; 3]), [0.0, 0.0, 0.2]);
    }

    #[test]
    fn garble_replaces_digits() {
        assert_eq!(garble("A=12.5"), b"\xffA=##.#".to_vec());
    }
}
