//! Line-oriented ASCII links over a serial port, a TCP connection (`tcp://HOST:PORT`, e.g. a PI
//! controller's GCS port 50000) or anything that reads and writes bytes with a timeout: the
//! transport the GCS and SCPI drivers share.
//!
//! Every way a device can misbehave on the wire becomes a [`DeviceError`] naming the device,
//! the command and what came back:
//! - nothing within the timeout → `Timeout`;
//! - bytes without a line terminator (or a binary block cut short) within the timeout, an
//!   over-long line, non-UTF-8 or control characters → `Garbled` with the text received
//!   (lossy, the first 200 bytes);
//! - end of file, hang-up, broken pipe, I/O error → `Disconnected`.
//!
//! Nothing here panics on device input.

use super::DeviceError;
use std::io::{self, Read, Write};
use std::time::{Duration, Instant};

/// Longest reply line accepted (bytes). Anything longer is garbage, not a reply.
pub const MAX_LINE: usize = 4096;

/// A byte stream with a settable read timeout: a serial port, a pseudo-terminal, or an
/// in-memory double in unit tests.
pub trait Transport: Read + Write + Send {
    /// Set the longest time one `read` may block.
    fn set_read_timeout(&mut self, timeout: Duration) -> io::Result<()>;
    /// Drop whatever was received and not read yet (stale replies after a fault).
    fn discard_input(&mut self) -> io::Result<()>;
}

impl Transport for Box<dyn serialport::SerialPort> {
    fn set_read_timeout(&mut self, timeout: Duration) -> io::Result<()> {
        self.set_timeout(timeout).map_err(io::Error::from)
    }
    fn discard_input(&mut self) -> io::Result<()> {
        self.clear(serialport::ClearBuffer::Input)
            .map_err(io::Error::from)
    }
}

impl Transport for serialport::TTYPort {
    fn set_read_timeout(&mut self, timeout: Duration) -> io::Result<()> {
        serialport::SerialPort::set_timeout(self, timeout).map_err(io::Error::from)
    }
    fn discard_input(&mut self) -> io::Result<()> {
        serialport::SerialPort::clear(self, serialport::ClearBuffer::Input).map_err(io::Error::from)
    }
}

/// A serial port opened by the drivers. On Unix it is opened exclusively (`TIOCEXCL`: a second
/// program cannot open it meanwhile) and the exclusivity is cleared again when the port is
/// closed. Pseudo-terminals keep the flag for as long as their master lives, so without the
/// clearing a non-root user could not reconnect to an emulator.
#[cfg(unix)]
struct SerialTransport(serialport::TTYPort);

#[cfg(unix)]
impl Read for SerialTransport {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        self.0.read(buf)
    }
}

#[cfg(unix)]
impl Write for SerialTransport {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.0.write(buf)
    }
    fn flush(&mut self) -> io::Result<()> {
        self.0.flush()
    }
}

#[cfg(unix)]
impl Transport for SerialTransport {
    fn set_read_timeout(&mut self, timeout: Duration) -> io::Result<()> {
        self.0.set_read_timeout(timeout)
    }
    fn discard_input(&mut self) -> io::Result<()> {
        self.0.discard_input()
    }
}

#[cfg(unix)]
impl Drop for SerialTransport {
    fn drop(&mut self) {
        let _ = self.0.set_exclusive(false);
    }
}

/// Open a serial port (real or pseudo-terminal) with 8N1, no flow control.
pub fn open_serial(
    device: &str,
    path: &str,
    baud: u32,
    timeout: Duration,
) -> Result<Box<dyn Transport>, DeviceError> {
    open_serial_with_flow(device, path, baud, timeout, false)
}

/// Open a serial port with 8N1 and, when `rtscts`, hardware (RTS/CTS) flow control (Thorlabs'
/// FTDI bridges).
pub fn open_serial_with_flow(
    device: &str,
    path: &str,
    baud: u32,
    timeout: Duration,
    rtscts: bool,
) -> Result<Box<dyn Transport>, DeviceError> {
    let flow = if rtscts {
        serialport::FlowControl::Hardware
    } else {
        serialport::FlowControl::None
    };
    let builder = serialport::new(path, baud)
        .timeout(timeout)
        .data_bits(serialport::DataBits::Eight)
        .parity(serialport::Parity::None)
        .stop_bits(serialport::StopBits::One)
        .flow_control(flow);
    #[cfg(unix)]
    let opened = builder
        .open_native()
        .map(|p| Box::new(SerialTransport(p)) as Box<dyn Transport>);
    #[cfg(not(unix))]
    let opened = builder.open().map(|p| Box::new(p) as Box<dyn Transport>);
    opened.map_err(|e| {
        let hint = match e.kind() {
            serialport::ErrorKind::NoDevice => {
                " (is it plugged in, and not opened by another program?)"
            }
            serialport::ErrorKind::Io(io::ErrorKind::PermissionDenied) => {
                " (permission denied: add yourself to the `dialout` group and log in again)"
            }
            serialport::ErrorKind::Io(io::ErrorKind::NotFound) => {
                " (no such port: check `port` in bfpscope.toml; `ls /dev/ttyUSB* /dev/ttyACM*`)"
            }
            _ => "",
        };
        DeviceError::Other {
            device: device.to_string(),
            detail: format!("cannot open {path}: {e}{hint}"),
        }
    })
}

/// The prefix of a TCP port in the config: `tcp://HOST:PORT`.
pub const TCP_PREFIX: &str = "tcp://";

/// A TCP connection to a controller (PI controllers speak GCS on port 50000): the same line
/// handling as a serial port, read timeouts from the socket.
pub struct TcpTransport(std::net::TcpStream);

impl Read for TcpTransport {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        self.0.read(buf)
    }
}

impl Write for TcpTransport {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.0.write(buf)
    }
    fn flush(&mut self) -> io::Result<()> {
        self.0.flush()
    }
}

impl Transport for TcpTransport {
    fn set_read_timeout(&mut self, timeout: Duration) -> io::Result<()> {
        self.0
            .set_read_timeout(Some(timeout.max(Duration::from_millis(1))))
    }
    /// Read whatever has arrived without waiting, and drop it.
    fn discard_input(&mut self) -> io::Result<()> {
        self.0.set_nonblocking(true)?;
        let mut chunk = [0u8; 512];
        let r = loop {
            match self.0.read(&mut chunk) {
                Ok(0) => break Ok(()), // closed: the next read reports it
                Ok(_) => continue,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break Ok(()),
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(e) => break Err(e),
            }
        };
        self.0.set_nonblocking(false)?;
        r
    }
}

/// Connect to `tcp://HOST:PORT` within `timeout`.
pub fn open_tcp(
    device: &str,
    url: &str,
    timeout: Duration,
) -> Result<Box<dyn Transport>, DeviceError> {
    use std::net::ToSocketAddrs;
    let fail = |detail: String| DeviceError::Other {
        device: device.to_string(),
        detail,
    };
    let addr = url.strip_prefix(TCP_PREFIX).unwrap_or(url);
    let addrs: Vec<std::net::SocketAddr> = addr
        .to_socket_addrs()
        .map_err(|e| {
            fail(format!(
                "cannot connect to {url}: {e} (write tcp://HOST:PORT, e.g. tcp://192.168.0.10:50000)"
            ))
        })?
        .collect();
    let mut last = None;
    for a in &addrs {
        match std::net::TcpStream::connect_timeout(a, timeout.max(Duration::from_millis(1))) {
            Ok(stream) => {
                let _ = stream.set_nodelay(true);
                stream
                    .set_read_timeout(Some(timeout.max(Duration::from_millis(1))))
                    .map_err(|e| fail(format!("cannot connect to {url}: {e}")))?;
                return Ok(Box::new(TcpTransport(stream)));
            }
            Err(e) => last = Some(e),
        }
    }
    let why = last.map_or_else(|| "no address".to_string(), |e| e.to_string());
    Err(fail(format!(
        "cannot connect to {url}: {why} (is the controller on, on this network, and its GCS port open? \
         PI controllers listen on 50000)"
    )))
}

/// Open `port`: `tcp://HOST:PORT` over TCP, anything else as a serial port at `baud`.
pub fn open_port(
    device: &str,
    port: &str,
    baud: u32,
    timeout: Duration,
) -> Result<Box<dyn Transport>, DeviceError> {
    if port.starts_with(TCP_PREFIX) {
        open_tcp(device, port, timeout)
    } else {
        open_serial(device, port, baud, timeout)
    }
}

/// Classify an I/O error: timeouts are timeouts, everything else means the link is gone.
pub fn io_error(device: &str, command: &str, timeout: Duration, e: &io::Error) -> DeviceError {
    match e.kind() {
        io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock => DeviceError::Timeout {
            device: device.to_string(),
            command: command.to_string(),
            timeout_ms: timeout.as_millis() as u64,
        },
        _ => DeviceError::Disconnected {
            device: device.to_string(),
            command: command.to_string(),
            detail: e.to_string(),
        },
    }
}

/// A device's port, the bytes read from it and not yet used, and the device's name (for
/// errors): what every device link (lines, binary blocks, APT messages) reads through.
pub struct Port {
    pub io: Box<dyn Transport>,
    pub device: String,
    pub buf: Vec<u8>,
}

impl Port {
    pub fn new(io: Box<dyn Transport>, device: impl Into<String>) -> Port {
        Port {
            io,
            device: device.into(),
            buf: Vec::new(),
        }
    }

    /// The one deadline-bounded read of every device link (lines, binary blocks, APT
    /// messages): read what the port has into `buf`, waiting at most until `deadline`.
    /// `Ok(true)`: bytes arrived; `Ok(false)`: the deadline passed with nothing new (the caller
    /// tells a silence from a partial reply by what `buf` holds). End of file is
    /// `Disconnected`, any other I/O error too (a timeout reported as an error is only the
    /// read's own, retried until the deadline).
    pub fn fill(
        &mut self,
        command: &str,
        deadline: Instant,
        timeout: Duration,
    ) -> Result<bool, DeviceError> {
        let Port { io, device, buf } = self;
        let mut chunk = [0u8; 16384];
        loop {
            let now = Instant::now();
            if now >= deadline {
                return Ok(false);
            }
            let remaining = (deadline - now).max(Duration::from_millis(1));
            if let Err(e) = io.set_read_timeout(remaining) {
                return Err(io_error(device, command, timeout, &e));
            }
            match io.read(&mut chunk) {
                Ok(0) => {
                    return Err(DeviceError::Disconnected {
                        device: device.to_string(),
                        command: command.to_string(),
                        detail: "end of file on the link (the device closed it)".into(),
                    })
                }
                Ok(n) => {
                    buf.extend_from_slice(&chunk[..n]);
                    return Ok(true);
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock
                    ) => {}
                Err(e) => return Err(io_error(device, command, timeout, &e)),
            }
        }
    }
}

/// Text of a byte string for messages: lossy UTF-8, control characters escaped by `{:?}`.
pub fn lossy(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// What one kind of command (its first word: `MOV`, `ERR?`, `#5`, `MEAS:QPD?`) cost on a
/// link: how often it was sent, the bytes each way (line ends included), the wall time spent
/// writing it and waiting for (and reading) its reply.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct CommandCost {
    pub n: u64,
    pub bytes_out: u64,
    pub bytes_in: u64,
    /// Seconds spent in writes.
    pub write_s: f64,
    /// Seconds from the end of the write to the reply's line end (the device's work, e.g. an
    /// acquisition, included).
    pub reply_s: f64,
}

/// Per-command costs of a link since the last [`LineLink::take_costs`], in first-use order.
pub type LinkCosts = Vec<(String, CommandCost)>;

/// The costs of several links as one (a stage's controllers, a KPZ101's cubes): each command's
/// costs summed over the links, in first-use order.
pub fn summed_costs(links: impl IntoIterator<Item = LinkCosts>) -> LinkCosts {
    let mut out: LinkCosts = Vec::new();
    for (name, c) in links.into_iter().flatten() {
        match out.iter_mut().find(|(n, _)| *n == name) {
            Some((_, o)) => {
                o.n += c.n;
                o.bytes_out += c.bytes_out;
                o.bytes_in += c.bytes_in;
                o.write_s += c.write_s;
                o.reply_s += c.reply_s;
            }
            None => out.push((name, c)),
        }
    }
    out
}

/// The replies on a link since it was opened (never reset): the device-side cost models
/// derive the link's reply latency from them before anything was measured for a scan
/// ([`LineLink::latency_s`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Turnarounds {
    /// Per reply (the first line after a command; the first [`Turnarounds::KEEP`]): seconds
    /// from the end of the command's write to the reply's line end, and the bytes of the
    /// command and the reply.
    pub replies: Vec<(f64, u64)>,
}

impl Turnarounds {
    /// Replies kept (the connect's queries and the first steps of a scan are enough).
    pub const KEEP: usize = 256;

    /// Add one reply (the first [`Turnarounds::KEEP`] are kept); `true` if it was kept.
    pub fn add(&mut self, reply_s: f64, bytes: u64) -> bool {
        let keep = self.replies.len() < Self::KEEP;
        if keep {
            self.replies.push((reply_s, bytes));
        }
        keep
    }

    /// The reply latency, s: the time from a command's end to its reply's end beyond the
    /// bytes' time on the wire (`bytes_per_s`: the serial rate, 10 bits per byte; `None`: TCP,
    /// no wire time), the median over the replies (at least the connect's identification and
    /// configuration queries; the median, because a few of those make the device work —
    /// switching servos on — and are not the link's). `None` before the first reply.
    pub fn latency_s(&self, bytes_per_s: Option<f64>) -> Option<f64> {
        let mut l: Vec<f64> = self
            .replies
            .iter()
            .map(|&(s, b)| (s - bytes_per_s.map_or(0.0, |r| b as f64 / r)).max(0.0))
            .collect();
        if l.is_empty() {
            return None;
        }
        l.sort_by(f64::total_cmp);
        let m = l.len() / 2;
        Some(if l.len() % 2 == 1 {
            l[m]
        } else {
            0.5 * (l[m - 1] + l[m])
        })
    }
}

/// The running cost entry of command `word` in `costs` (a new one at the end if none yet).
pub fn cost_of<'a>(costs: &'a mut LinkCosts, word: &str) -> &'a mut CommandCost {
    let i = match costs.iter().position(|(w, _)| w == word) {
        Some(i) => i,
        None => {
            costs.push((word.to_string(), CommandCost::default()));
            costs.len() - 1
        }
    };
    &mut costs[i].1
}

/// A line-terminated (LF, optional CR before it) ASCII command link, which also reads IEEE
/// 488.2 definite-length binary blocks (`#<k><len><bytes>`).
pub struct LineLink {
    port: Port,
    /// Appended to every command sent (LF; a Red Pitaya's SCPI server: CR LF).
    terminator: &'static [u8],
    /// Longest reply line or block accepted, bytes (anything longer is garbage).
    max_reply: usize,
    /// Default reply timeout.
    pub timeout: Duration,
    costs: LinkCosts,
    turnarounds: Turnarounds,
    /// Bytes of the last command sent, until its reply is read.
    pending_out: Option<u64>,
    /// The last reply's lines are still being added to its turnaround.
    reply_open: bool,
}

impl LineLink {
    pub fn new(io: Box<dyn Transport>, device: impl Into<String>, timeout: Duration) -> Self {
        Self {
            port: Port::new(io, device),
            terminator: b"\n",
            max_reply: MAX_LINE,
            timeout,
            costs: Vec::new(),
            turnarounds: Turnarounds::default(),
            pending_out: None,
            reply_open: false,
        }
    }

    /// Commands end with `terminator` instead of LF; replies (lines, blocks) up to `max_reply`
    /// bytes are accepted.
    pub fn with_framing(mut self, terminator: &'static [u8], max_reply: usize) -> Self {
        self.terminator = terminator;
        self.max_reply = max_reply;
        self
    }

    /// The replies so far (see [`Turnarounds`]).
    pub fn turnarounds(&self) -> &Turnarounds {
        &self.turnarounds
    }

    /// The link's reply latency, s ([`Turnarounds::latency_s`] over the replies so far).
    pub fn latency_s(&self, bytes_per_s: Option<f64>) -> Option<f64> {
        self.turnarounds.latency_s(bytes_per_s)
    }

    /// The costs per command word since the last call (and start counting anew).
    pub fn take_costs(&mut self) -> LinkCosts {
        std::mem::take(&mut self.costs)
    }

    fn cost(&mut self, command: &str) -> &mut CommandCost {
        cost_of(
            &mut self.costs,
            command.split_whitespace().next().unwrap_or(""),
        )
    }

    pub fn device(&self) -> &str {
        &self.port.device
    }

    pub fn set_device(&mut self, device: impl Into<String>) {
        self.port.device = device.into();
    }

    /// Forget stale input (ours and the port's) before a new exchange.
    pub fn discard_input(&mut self) {
        self.port.buf.clear();
        // Best effort: a port that cannot flush will show its problem on the next read/write.
        let _ = self.port.io.discard_input();
    }

    /// Send one command line (the terminator appended).
    pub fn send(&mut self, command: &str) -> Result<(), DeviceError> {
        let mut line = Vec::with_capacity(command.len() + 2);
        line.extend_from_slice(command.as_bytes());
        line.extend_from_slice(self.terminator);
        self.send_raw(&line, command)
    }

    /// Send raw bytes as they are (a command line with its terminator, or PI's single-character
    /// commands such as `#5`, 0x05, with none); `label` names them in errors and costs.
    pub fn send_raw(&mut self, bytes: &[u8], label: &str) -> Result<(), DeviceError> {
        let timeout = self.timeout;
        let t0 = Instant::now();
        let r = self
            .port
            .io
            .write_all(bytes)
            .and_then(|_| self.port.io.flush())
            .map_err(|e| io_error(&self.port.device, label, timeout, &e));
        let c = self.cost(label);
        c.n += 1;
        c.bytes_out += bytes.len() as u64;
        c.write_s += t0.elapsed().as_secs_f64();
        self.pending_out = Some(bytes.len() as u64);
        self.reply_open = false;
        r
    }

    /// Read one reply line to `command` (terminator and a trailing CR removed, other
    /// whitespace kept), waiting at most `timeout` in total.
    pub fn read_line(&mut self, command: &str, timeout: Duration) -> Result<String, DeviceError> {
        let t0 = Instant::now();
        let r = self.read_line_inner(command, timeout);
        self.account(command, t0, r.as_ref().ok().map(|l| l.len() + 1));
        r
    }

    /// Count a reply to `command` that was read from `t0` on: its bytes (`None`: it failed) and
    /// time in the command's cost, and in the command's turnaround — from its write to the end
    /// of its reply, every line of a multi-line reply (`TMN?` answers one line per axis).
    fn account(&mut self, command: &str, t0: Instant, bytes: Option<usize>) {
        let dt = t0.elapsed().as_secs_f64();
        let n = bytes.unwrap_or(0) as u64;
        let c = self.cost(command);
        c.bytes_in += n;
        c.reply_s += dt;
        if bytes.is_some() {
            match self.pending_out.take() {
                Some(out) => self.reply_open = self.turnarounds.add(dt, out + n),
                None if self.reply_open => {
                    if let Some(last) = self.turnarounds.replies.last_mut() {
                        last.0 += dt;
                        last.1 += n;
                    }
                }
                None => {}
            }
        }
    }

    fn read_line_inner(&mut self, command: &str, timeout: Duration) -> Result<String, DeviceError> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(i) = self.port.buf.iter().position(|&b| b == b'\n') {
                let mut line: Vec<u8> = self.port.buf.drain(..=i).collect();
                line.pop();
                if line.last() == Some(&b'\r') {
                    line.pop();
                }
                return self.check_text(command, line);
            }
            if self.port.buf.len() > self.max_reply {
                let reply = lossy(&self.port.buf[..200.min(self.port.buf.len())]);
                self.port.buf.clear();
                return Err(self.garbled(
                    command,
                    format!("{reply} [no line end after {} bytes]", self.max_reply),
                ));
            }
            if !self.port.fill(command, deadline, timeout)? {
                return Err(self.timed_out(command, timeout));
            }
        }
    }

    /// Read a definite-length block `#<k><len digits><len bytes>` (IEEE 488.2) and the line end
    /// after it, waiting at most `timeout` in total; a bad header or a block cut short is
    /// `Garbled`, showing what came.
    pub fn read_block(&mut self, command: &str, timeout: Duration) -> Result<Vec<u8>, DeviceError> {
        let t0 = Instant::now();
        let r = self.read_block_inner(command, t0 + timeout, timeout);
        self.account(command, t0, r.as_ref().ok().map(|(_, n)| *n));
        r.map(|(data, _)| data)
    }

    fn read_block_inner(
        &mut self,
        command: &str,
        deadline: Instant,
        timeout: Duration,
    ) -> Result<(Vec<u8>, usize), DeviceError> {
        let need = |s: &mut Self, n: usize| -> Result<(), DeviceError> {
            while s.port.buf.len() < n {
                if !s.port.fill(command, deadline, timeout)? {
                    return Err(s.timed_out(command, timeout));
                }
            }
            Ok(())
        };
        let bad = |s: &mut Self, why: &str| {
            let shown = lossy(&s.port.buf[..80.min(s.port.buf.len())]);
            s.port.buf.clear();
            s.garbled(command, format!("{shown} [{why}]"))
        };
        need(self, 2)?;
        if self.port.buf[0] != b'#' {
            return Err(bad(self, "expected a binary block starting with `#`"));
        }
        let k = match (self.port.buf[1] as char).to_digit(10) {
            Some(k @ 1..=9) => k as usize,
            _ => return Err(bad(self, "bad block header: digit count")),
        };
        need(self, 2 + k)?;
        let len: usize = match std::str::from_utf8(&self.port.buf[2..2 + k])
            .ok()
            .and_then(|t| t.parse().ok())
        {
            Some(l) if l <= self.max_reply => l,
            _ => return Err(bad(self, "bad block header: length")),
        };
        let start = 2 + k;
        need(self, start + len)?;
        let data: Vec<u8> = self.port.buf[start..start + len].to_vec();
        self.port.buf.drain(..start + len);
        // the line end after the block (may still be on its way)
        let short = Instant::now() + Duration::from_millis(50).min(timeout);
        while self.port.buf.len() < 2 && !self.port.buf.starts_with(b"\n") {
            if !matches!(self.port.fill(command, short, timeout), Ok(true)) {
                break;
            }
        }
        if self.port.buf.starts_with(b"\r\n") {
            self.port.buf.drain(..2);
        } else if self.port.buf.starts_with(b"\n") {
            self.port.buf.drain(..1);
        }
        // the header `#<k><len>` and the data: the block's bytes on the wire
        let n = start + data.len();
        Ok((data, n))
    }

    /// Send `command` and read one reply line.
    pub fn query(&mut self, command: &str) -> Result<String, DeviceError> {
        self.query_with_timeout(command, self.timeout)
    }

    pub fn query_with_timeout(
        &mut self,
        command: &str,
        timeout: Duration,
    ) -> Result<String, DeviceError> {
        self.discard_input();
        self.send(command)?;
        self.read_line(command, timeout)
    }

    /// A timeout. If part of a line arrived, that is a garbled (unterminated) reply instead,
    /// and the message shows it.
    fn timed_out(&mut self, command: &str, timeout: Duration) -> DeviceError {
        if self.port.buf.is_empty() {
            DeviceError::Timeout {
                device: self.port.device.clone(),
                command: command.to_string(),
                timeout_ms: timeout.as_millis() as u64,
            }
        } else {
            let reply = lossy(&self.port.buf[..200.min(self.port.buf.len())]);
            let n = self.port.buf.len();
            self.port.buf.clear();
            self.garbled(
                command,
                format!(
                    "{reply} [{n} bytes, incomplete within {} ms]",
                    timeout.as_millis()
                ),
            )
        }
    }

    pub fn garbled(&self, command: &str, reply: impl Into<String>) -> DeviceError {
        DeviceError::Garbled {
            device: self.port.device.clone(),
            command: command.to_string(),
            reply: reply.into(),
        }
    }

    fn check_text(&self, command: &str, line: Vec<u8>) -> Result<String, DeviceError> {
        match String::from_utf8(line) {
            Ok(s) if s.chars().all(|c| c == '\t' || !c.is_control()) && s.is_ascii() => Ok(s),
            Ok(s) => Err(self.garbled(command, s)),
            Err(e) => Err(self.garbled(command, lossy(e.as_bytes()))),
        }
    }
}

/// An in-memory transport for unit tests: replies are scripted per written line.
#[cfg(test)]
pub(crate) mod mock {
    use super::*;
    use std::collections::VecDeque;

    /// Each command written pops the next scripted reply (raw bytes, may be empty = silence).
    pub struct Scripted {
        pub replies: VecDeque<Vec<u8>>,
        pending: Vec<u8>,
        written: Vec<u8>,
        pub log: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
    }

    impl Scripted {
        pub fn new(replies: Vec<Vec<u8>>) -> Self {
            Self {
                replies: replies.into(),
                pending: Vec::new(),
                written: Vec::new(),
                log: Default::default(),
            }
        }
    }

    impl Read for Scripted {
        fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
            if self.pending.is_empty() {
                return Err(io::Error::new(io::ErrorKind::TimedOut, "mock timeout"));
            }
            let n = buf.len().min(self.pending.len());
            buf[..n].copy_from_slice(&self.pending[..n]);
            self.pending.drain(..n);
            Ok(n)
        }
    }

    impl Write for Scripted {
        fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
            self.written.extend_from_slice(buf);
            while let Some(i) = self.written.iter().position(|&b| b == b'\n') {
                let line: Vec<u8> = self.written.drain(..=i).collect();
                self.log
                    .lock()
                    .unwrap()
                    .push(lossy(&line[..line.len() - 1]));
                if let Some(r) = self.replies.pop_front() {
                    self.pending.extend_from_slice(&r);
                }
            }
            Ok(buf.len())
        }
        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    /// A link named "dev" (20 ms timeout) whose device answers each command with the next of
    /// `replies`.
    pub fn link(replies: Vec<&[u8]>) -> LineLink {
        let s = Scripted::new(replies.into_iter().map(|r| r.to_vec()).collect());
        LineLink::new(Box::new(s), "dev", Duration::from_millis(20))
    }

    impl Transport for Scripted {
        fn set_read_timeout(&mut self, _timeout: Duration) -> io::Result<()> {
            Ok(())
        }
        fn discard_input(&mut self) -> io::Result<()> {
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::mock::link;
    use super::*;

    #[test]
    fn summed_costs_add_each_command_over_links_in_first_use_order() {
        let cost = |n, bytes_out, bytes_in, write_s, reply_s| CommandCost {
            n,
            bytes_out,
            bytes_in,
            write_s,
            reply_s,
        };
        let a = vec![
            ("MOV".to_string(), cost(2, 20, 0, 0.5, 0.0)),
            ("ERR?".to_string(), cost(1, 5, 2, 0.25, 1.0)),
        ];
        let b = vec![
            ("POS?".to_string(), cost(3, 15, 30, 0.125, 2.0)),
            ("MOV".to_string(), cost(1, 10, 0, 0.25, 0.0)),
        ];
        assert_eq!(
            summed_costs([a, b]),
            vec![
                ("MOV".to_string(), cost(3, 30, 0, 0.75, 0.0)),
                ("ERR?".to_string(), cost(1, 5, 2, 0.25, 1.0)),
                ("POS?".to_string(), cost(3, 15, 30, 0.125, 2.0)),
            ]
        );
    }

    #[test]
    fn reads_lines_and_strips_cr() {
        let mut l = link(vec![b"hello\r\n"]);
        assert_eq!(l.query("Q?").unwrap(), "hello");
    }

    #[test]
    fn silence_is_timeout_partial_is_garbled() {
        let mut l = link(vec![b""]);
        match l.query("Q?") {
            Err(DeviceError::Timeout {
                device,
                command,
                timeout_ms,
            }) => {
                assert_eq!(
                    (device.as_str(), command.as_str(), timeout_ms),
                    ("dev", "Q?", 20)
                );
            }
            other => panic!("{other:?}"),
        }
        let mut l = link(vec![b"A=1.0"]);
        match l.query("POS?") {
            Err(DeviceError::Garbled { reply, command, .. }) => {
                assert!(reply.starts_with("A=1.0"), "{reply}");
                assert_eq!(command, "POS?");
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn binary_and_overlong_are_garbled() {
        let mut l = link(vec![b"\xff\xfe\x01\n"]);
        assert!(matches!(l.query("Q?"), Err(DeviceError::Garbled { .. })));
        let long = vec![b'x'; MAX_LINE + 10];
        let mut l = link(vec![&long]);
        assert!(matches!(l.query("Q?"), Err(DeviceError::Garbled { .. })));
    }
}
