//! Thorlabs APT binary protocol (K-Cubes, T-Cubes) over their FTDI USB-serial bridge:
//! framing, the link that waits for a reply, and the message ids bfpscope uses.
//!
//! Learned from Thorlabs' "APT Communications Protocol" document and from the open
//! implementations labs use (pylablib's Kinesis classes, the `thorlabs_apt_protocol`
//! package); written here from scratch.
//!
//! **Frame**: a 6-byte header, then an optional data packet, all little-endian.
//!
//! ```text
//! short:  id(u16 LE) | param1 | param2       | dest        | source
//! long:   id(u16 LE) | length(u16 LE)        | dest | 0x80 | source   then `length` data bytes
//! ```
//!
//! The host is `0x01`; a single-channel USB unit (every K-Cube) is `0x50`. Setting messages
//! (`SET_…`) are never acknowledged; requests (`REQ_…`) are answered with the matching `GET_…`;
//! a device ignores a message id it does not know (no reply, no error). Errors a device detects
//! come as `MGMSG_HW_RESPONSE` / `MGMSG_HW_RICHRESPONSE` (a code and, for the rich form, a
//! text). Serial settings: 115200 baud, 8N1, RTS/CTS flow control.

pub mod config;
pub use config::FAMILY;
pub mod emulator;
pub mod kpa101;
pub mod kpz101;

use super::link::{CommandCost, LinkCosts, Port, Transport, Turnarounds};
use super::DeviceError;
use std::io;
use std::time::{Duration, Instant};

/// The host (this program) as source or destination.
pub const HOST: u8 = 0x01;
/// A generic single-channel USB unit (every K-Cube).
pub const USB_UNIT: u8 = 0x50;
/// Flag on the destination byte: a data packet follows the header.
pub const DATA_FLAG: u8 = 0x80;
/// Longest data packet accepted (bytes). The messages used here carry at most 84; a header
/// announcing more is line noise, not a message.
pub const MAX_DATA: usize = 255;
/// Channel 1, the only channel of a K-Cube (the `chan ident` of the messages).
pub const CHAN1: u8 = 0x01;

/// Message ids used by bfpscope (names as in Thorlabs' document).
pub mod id {
    pub const HW_DISCONNECT: u16 = 0x0002;
    pub const HW_REQ_INFO: u16 = 0x0005;
    pub const HW_GET_INFO: u16 = 0x0006;
    pub const HW_START_UPDATEMSGS: u16 = 0x0011;
    pub const HW_STOP_UPDATEMSGS: u16 = 0x0012;
    pub const HW_NO_FLASH_PROGRAMMING: u16 = 0x0018;
    pub const HW_RESPONSE: u16 = 0x0080;
    pub const HW_RICHRESPONSE: u16 = 0x0081;
    pub const MOD_SET_CHANENABLESTATE: u16 = 0x0210;
    pub const MOD_REQ_CHANENABLESTATE: u16 = 0x0211;
    pub const MOD_GET_CHANENABLESTATE: u16 = 0x0212;
    pub const MOD_IDENTIFY: u16 = 0x0223;
    pub const PZ_SET_POSCONTROLMODE: u16 = 0x0640;
    pub const PZ_REQ_POSCONTROLMODE: u16 = 0x0641;
    pub const PZ_GET_POSCONTROLMODE: u16 = 0x0642;
    pub const PZ_SET_OUTPUTVOLTS: u16 = 0x0643;
    pub const PZ_REQ_OUTPUTVOLTS: u16 = 0x0644;
    pub const PZ_GET_OUTPUTVOLTS: u16 = 0x0645;
    pub const PZ_SET_OUTPUTPOS: u16 = 0x0646;
    pub const PZ_REQ_OUTPUTPOS: u16 = 0x0647;
    pub const PZ_GET_OUTPUTPOS: u16 = 0x0648;
    pub const PZ_REQ_MAXTRAVEL: u16 = 0x0650;
    pub const PZ_GET_MAXTRAVEL: u16 = 0x0651;
    pub const PZ_SET_ZERO: u16 = 0x0658;
    pub const PZ_REQ_PZSTATUSUPDATE: u16 = 0x0660;
    pub const PZ_GET_PZSTATUSUPDATE: u16 = 0x0661;
    pub const QUAD_SET_PARAMS: u16 = 0x0870;
    pub const QUAD_REQ_PARAMS: u16 = 0x0871;
    pub const QUAD_GET_PARAMS: u16 = 0x0872;
    pub const QUAD_REQ_STATUSUPDATE: u16 = 0x0880;
    pub const QUAD_GET_STATUSUPDATE: u16 = 0x0881;

    /// The document's name of a message id, for messages (`0x0871 MGMSG_QUAD_REQ_PARAMS`).
    pub fn name(id: u16) -> &'static str {
        match id {
            HW_DISCONNECT => "MGMSG_HW_DISCONNECT",
            HW_REQ_INFO => "MGMSG_HW_REQ_INFO",
            HW_GET_INFO => "MGMSG_HW_GET_INFO",
            HW_START_UPDATEMSGS => "MGMSG_HW_START_UPDATEMSGS",
            HW_STOP_UPDATEMSGS => "MGMSG_HW_STOP_UPDATEMSGS",
            HW_NO_FLASH_PROGRAMMING => "MGMSG_HW_NO_FLASH_PROGRAMMING",
            HW_RESPONSE => "MGMSG_HW_RESPONSE",
            HW_RICHRESPONSE => "MGMSG_HW_RICHRESPONSE",
            MOD_SET_CHANENABLESTATE => "MGMSG_MOD_SET_CHANENABLESTATE",
            MOD_REQ_CHANENABLESTATE => "MGMSG_MOD_REQ_CHANENABLESTATE",
            MOD_GET_CHANENABLESTATE => "MGMSG_MOD_GET_CHANENABLESTATE",
            MOD_IDENTIFY => "MGMSG_MOD_IDENTIFY",
            PZ_SET_POSCONTROLMODE => "MGMSG_PZ_SET_POSCONTROLMODE",
            PZ_REQ_POSCONTROLMODE => "MGMSG_PZ_REQ_POSCONTROLMODE",
            PZ_GET_POSCONTROLMODE => "MGMSG_PZ_GET_POSCONTROLMODE",
            PZ_SET_OUTPUTVOLTS => "MGMSG_PZ_SET_OUTPUTVOLTS",
            PZ_REQ_OUTPUTVOLTS => "MGMSG_PZ_REQ_OUTPUTVOLTS",
            PZ_GET_OUTPUTVOLTS => "MGMSG_PZ_GET_OUTPUTVOLTS",
            PZ_SET_OUTPUTPOS => "MGMSG_PZ_SET_OUTPUTPOS",
            PZ_REQ_OUTPUTPOS => "MGMSG_PZ_REQ_OUTPUTPOS",
            PZ_GET_OUTPUTPOS => "MGMSG_PZ_GET_OUTPUTPOS",
            PZ_REQ_MAXTRAVEL => "MGMSG_PZ_REQ_MAXTRAVEL",
            PZ_GET_MAXTRAVEL => "MGMSG_PZ_GET_MAXTRAVEL",
            PZ_SET_ZERO => "MGMSG_PZ_SET_ZERO",
            PZ_REQ_PZSTATUSUPDATE => "MGMSG_PZ_REQ_PZSTATUSUPDATE",
            PZ_GET_PZSTATUSUPDATE => "MGMSG_PZ_GET_PZSTATUSUPDATE",
            QUAD_SET_PARAMS => "MGMSG_QUAD_SET_PARAMS",
            QUAD_REQ_PARAMS => "MGMSG_QUAD_REQ_PARAMS",
            QUAD_GET_PARAMS => "MGMSG_QUAD_GET_PARAMS",
            QUAD_REQ_STATUSUPDATE => "MGMSG_QUAD_REQ_STATUSUPDATE",
            QUAD_GET_STATUSUPDATE => "MGMSG_QUAD_GET_STATUSUPDATE",
            _ => "unknown message",
        }
    }
}

/// One APT message: a short one (two parameter bytes) or a long one (a data packet).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Message {
    pub id: u16,
    pub param1: u8,
    pub param2: u8,
    /// `Some(bytes)`: a long message carrying this data packet (the parameters are unused).
    pub data: Option<Vec<u8>>,
    pub dest: u8,
    pub source: u8,
}

impl Message {
    /// A short message from the host to the USB unit.
    pub fn short(id: u16, param1: u8, param2: u8) -> Self {
        Self {
            id,
            param1,
            param2,
            data: None,
            dest: USB_UNIT,
            source: HOST,
        }
    }

    /// A long message from the host to the USB unit.
    pub fn long(id: u16, data: Vec<u8>) -> Self {
        Self {
            id,
            param1: 0,
            param2: 0,
            data: Some(data),
            dest: USB_UNIT,
            source: HOST,
        }
    }

    /// The same message addressed from the device back to the host (emulators).
    pub fn reply(mut self) -> Self {
        self.dest = HOST;
        self.source = USB_UNIT;
        self
    }

    /// The bytes on the wire.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(6 + self.data.as_ref().map_or(0, Vec::len));
        out.extend_from_slice(&self.id.to_le_bytes());
        match &self.data {
            None => {
                out.extend_from_slice(&[self.param1, self.param2, self.dest & !DATA_FLAG]);
            }
            Some(d) => {
                out.extend_from_slice(&(d.len() as u16).to_le_bytes());
                out.push(self.dest | DATA_FLAG);
            }
        }
        out.push(self.source);
        if let Some(d) = &self.data {
            out.extend_from_slice(d);
        }
        out
    }

    /// For messages: `0x0646 MGMSG_PZ_SET_OUTPUTPOS [01 00 ff 3f]` or
    /// `0x0005 MGMSG_HW_REQ_INFO (00, 00)`.
    pub fn describe(&self) -> String {
        let head = format!("0x{:04X} {}", self.id, id::name(self.id));
        match &self.data {
            None => format!("{head} ({:02x}, {:02x})", self.param1, self.param2),
            Some(d) => format!("{head} [{}]", hex(d)),
        }
    }

    /// The data packet (empty for a short message).
    pub fn bytes(&self) -> &[u8] {
        self.data.as_deref().unwrap_or(&[])
    }
}

/// Bytes as `01 00 ff` for messages.
pub fn hex(bytes: &[u8]) -> String {
    bytes
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// What [`parse`] makes of the front of a byte buffer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Parsed {
    /// A whole message, and how many bytes it took.
    Message(Message, usize),
    /// Not enough bytes yet.
    Incomplete,
    /// The header cannot be an APT header (why); the caller must resynchronise.
    Invalid(String),
}

/// Parse one message from the front of `buf`. `expect_dest` is the address this end listens on
/// (the host for a driver, the USB unit for an emulator): a header addressed elsewhere, with
/// a source other than the peer, or announcing more than [`MAX_DATA`] bytes is `Invalid`.
pub fn parse(buf: &[u8], expect_dest: u8) -> Parsed {
    if buf.len() < 6 {
        return Parsed::Incomplete;
    }
    let id = u16::from_le_bytes([buf[0], buf[1]]);
    let dest_raw = buf[4];
    let source = buf[5];
    let peer = if expect_dest == HOST { USB_UNIT } else { HOST };
    let dest = dest_raw & !DATA_FLAG;
    if dest != expect_dest || source != peer {
        return Parsed::Invalid(format!(
            "header [{}]: destination 0x{dest_raw:02x} / source 0x{source:02x}, expected 0x{expect_dest:02x} \
             (| 0x80 with data) / 0x{peer:02x}",
            hex(&buf[..6])
        ));
    }
    if dest_raw & DATA_FLAG == 0 {
        return Parsed::Message(
            Message {
                id,
                param1: buf[2],
                param2: buf[3],
                data: None,
                dest,
                source,
            },
            6,
        );
    }
    let len = u16::from_le_bytes([buf[2], buf[3]]) as usize;
    if len > MAX_DATA {
        return Parsed::Invalid(format!(
            "header [{}] announces {len} data bytes (at most {MAX_DATA})",
            hex(&buf[..6])
        ));
    }
    if buf.len() < 6 + len {
        return Parsed::Incomplete;
    }
    Parsed::Message(
        Message {
            id,
            param1: 0,
            param2: 0,
            data: Some(buf[6..6 + len].to_vec()),
            dest,
            source,
        },
        6 + len,
    )
}

/// `MGMSG_HW_GET_INFO`: what a device says about itself (84-byte data packet).
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct HwInfo {
    pub serial: u32,
    /// Model number, e.g. `KPZ101`.
    pub model: String,
    pub hw_type: u16,
    /// Firmware version `major.interim.minor`.
    pub firmware: String,
    pub notes: String,
    pub hw_version: u16,
    pub mod_state: u16,
    pub channels: u16,
}

/// Length of the `MGMSG_HW_GET_INFO` data packet.
pub const HW_INFO_LEN: usize = 84;

fn text(bytes: &[u8]) -> String {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    String::from_utf8_lossy(&bytes[..end]).trim().to_string()
}

impl HwInfo {
    /// Decode the data packet; `None` unless it has the documented length.
    pub fn decode(d: &[u8]) -> Option<Self> {
        if d.len() != HW_INFO_LEN {
            return None;
        }
        let u16_at = |i: usize| u16::from_le_bytes([d[i], d[i + 1]]);
        Some(Self {
            serial: u32::from_le_bytes([d[0], d[1], d[2], d[3]]),
            model: text(&d[4..12]),
            hw_type: u16_at(12),
            firmware: format!("{}.{}.{}", d[16], d[15], d[14]),
            notes: text(&d[18..66]),
            hw_version: u16_at(78),
            mod_state: u16_at(80),
            channels: u16_at(82),
        })
    }

    /// Encode as the data packet (emulators). Firmware is given as (major, interim, minor).
    pub fn encode(
        serial: u32,
        model: &str,
        hw_type: u16,
        fw: (u8, u8, u8),
        notes: &str,
        channels: u16,
    ) -> Vec<u8> {
        let mut d = vec![0u8; HW_INFO_LEN];
        d[0..4].copy_from_slice(&serial.to_le_bytes());
        for (i, b) in model.bytes().take(8).enumerate() {
            d[4 + i] = b;
        }
        d[12..14].copy_from_slice(&hw_type.to_le_bytes());
        d[14] = fw.2;
        d[15] = fw.1;
        d[16] = fw.0;
        for (i, b) in notes.bytes().take(48).enumerate() {
            d[18 + i] = b;
        }
        d[78..80].copy_from_slice(&1u16.to_le_bytes());
        d[82..84].copy_from_slice(&channels.to_le_bytes());
        d
    }
}

/// Open an APT device's port: 115200 baud 8N1 with RTS/CTS flow control, as Thorlabs
/// specifies for the FTDI bridge.
pub fn open_apt_serial(
    device: &str,
    path: &str,
    timeout: Duration,
) -> Result<Box<dyn Transport>, DeviceError> {
    super::link::open_serial_with_flow(device, path, 115_200, timeout, true)
}

/// A binary APT link: send messages, wait for a given reply id.
pub struct AptLink {
    port: Port,
    pub timeout: Duration,
    /// Messages received while waiting for another id (unsolicited status updates, replies
    /// to nothing), counted and skipped.
    pub skipped: usize,
    /// What each message (by name) cost since the last [`AptLink::take_costs`].
    costs: LinkCosts,
    /// Every request's turnaround since the link was opened (the link model's latency).
    turnarounds: Turnarounds,
}

/// APT's fixed line: 115200 baud, 8N1 (10 bits per byte), bytes per second.
pub const APT_BYTES_PER_S: f64 = 115_200.0 / 10.0;

impl AptLink {
    pub fn new(io: Box<dyn Transport>, device: impl Into<String>, timeout: Duration) -> Self {
        Self {
            port: Port::new(io, device),
            timeout,
            skipped: 0,
            costs: Vec::new(),
            turnarounds: Turnarounds::default(),
        }
    }

    /// The costs per message since the last call (and start counting anew).
    pub fn take_costs(&mut self) -> LinkCosts {
        std::mem::take(&mut self.costs)
    }

    /// The link's reply latency beyond the bytes at 115200 baud, s (the median over every
    /// request so far, see [`Turnarounds::latency_s`]); `None` before the first.
    pub fn latency_s(&self) -> Option<f64> {
        self.turnarounds.latency_s(Some(APT_BYTES_PER_S))
    }

    fn cost(&mut self, id: u16) -> &mut CommandCost {
        super::link::cost_of(&mut self.costs, id::name(id))
    }

    pub fn device(&self) -> &str {
        &self.port.device
    }

    pub fn set_device(&mut self, device: impl Into<String>) {
        self.port.device = device.into();
    }

    /// The start of every connect: flash writes off (`HW_NO_FLASH_PROGRAMMING`), no unsolicited
    /// status updates (`HW_STOP_UPDATEMSGS`), then the unit's identity (`HW_REQ_INFO` →
    /// `HW_GET_INFO`); a reply of the wrong length is garbled.
    pub fn identify(&mut self) -> Result<HwInfo, DeviceError> {
        self.send(&Message::short(id::HW_NO_FLASH_PROGRAMMING, 0, 0))?;
        self.send(&Message::short(id::HW_STOP_UPDATEMSGS, 0, 0))?;
        let req = Message::short(id::HW_REQ_INFO, 0, 0);
        let r = self.request(&req, id::HW_GET_INFO)?;
        HwInfo::decode(r.bytes()).ok_or_else(|| DeviceError::Garbled {
            device: self.port.device.clone(),
            command: req.describe(),
            reply: format!(
                "{} with {} data bytes, expected {HW_INFO_LEN}",
                r.describe(),
                r.bytes().len()
            ),
        })
    }

    fn io_error(&self, command: &str, e: &io::Error) -> DeviceError {
        match e.kind() {
            io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock => DeviceError::Timeout {
                device: self.port.device.clone(),
                command: command.to_string(),
                timeout_ms: self.timeout.as_millis() as u64,
            },
            _ => DeviceError::Disconnected {
                device: self.port.device.clone(),
                command: command.to_string(),
                detail: e.to_string(),
            },
        }
    }

    /// Send one message (no reply expected: `SET_…` messages are never acknowledged).
    pub fn send(&mut self, m: &Message) -> Result<(), DeviceError> {
        let bytes = m.encode();
        let t0 = Instant::now();
        let r = self
            .port
            .io
            .write_all(&bytes)
            .and_then(|_| self.port.io.flush())
            .map_err(|e| self.io_error(&m.describe(), &e));
        let c = self.cost(m.id);
        c.n += 1;
        c.bytes_out += bytes.len() as u64;
        c.write_s += t0.elapsed().as_secs_f64();
        r
    }

    /// Send `m` and wait for a message with id `reply` (other messages are skipped), at most
    /// `timeout` in all. `MGMSG_HW_RESPONSE`/`RICHRESPONSE` become `Controller` errors.
    pub fn request(&mut self, m: &Message, reply: u16) -> Result<Message, DeviceError> {
        self.port.buf.clear();
        let _ = self.port.io.discard_input();
        self.send(m)?;
        let timeout = self.timeout;
        let t0 = Instant::now();
        let r = self.wait_for(&m.describe(), reply, timeout);
        let dt = t0.elapsed().as_secs_f64();
        let back = r.as_ref().map_or(0, |msg| msg.encode().len() as u64);
        let c = self.cost(m.id);
        c.bytes_in += back;
        c.reply_s += dt;
        if r.is_ok() {
            self.turnarounds.add(dt, m.encode().len() as u64 + back);
        }
        r
    }

    /// Wait for a message with id `reply`.
    pub fn wait_for(
        &mut self,
        command: &str,
        reply: u16,
        timeout: Duration,
    ) -> Result<Message, DeviceError> {
        let deadline = Instant::now() + timeout;
        loop {
            match parse(&self.port.buf, HOST) {
                Parsed::Message(msg, used) => {
                    self.port.buf.drain(..used);
                    if msg.id == reply {
                        return Ok(msg);
                    }
                    if msg.id == id::HW_RESPONSE || msg.id == id::HW_RICHRESPONSE {
                        return Err(self.device_response(command, &msg));
                    }
                    self.skipped += 1;
                    continue;
                }
                Parsed::Invalid(why) => {
                    let got = hex(&self.port.buf);
                    self.port.buf.clear();
                    let _ = self.port.io.discard_input();
                    return Err(DeviceError::Garbled {
                        device: self.port.device.clone(),
                        command: command.to_string(),
                        reply: format!("[{got}]: {why}"),
                    });
                }
                Parsed::Incomplete => {}
            }
            if !self.port.fill(command, deadline, timeout)? {
                return Err(if self.port.buf.is_empty() {
                    DeviceError::Timeout {
                        device: self.port.device.clone(),
                        command: command.to_string(),
                        timeout_ms: timeout.as_millis() as u64,
                    }
                } else {
                    let got = hex(&self.port.buf);
                    self.port.buf.clear();
                    DeviceError::Garbled {
                        device: self.port.device.clone(),
                        command: command.to_string(),
                        reply: format!(
                            "[{got}]: an incomplete message within {} ms (waiting for 0x{reply:04X} {})",
                            timeout.as_millis(),
                            id::name(reply)
                        ),
                    }
                });
            }
        }
    }

    /// An error report from the device: `MGMSG_HW_RESPONSE` (a short message, no detail) or
    /// `MGMSG_HW_RICHRESPONSE` (data: message id u16, code u16, 64 characters of text).
    fn device_response(&self, command: &str, msg: &Message) -> DeviceError {
        let d = msg.bytes();
        let (code, message) = if msg.id == id::HW_RICHRESPONSE && d.len() >= 4 {
            let about = u16::from_le_bytes([d[0], d[1]]);
            let code = u16::from_le_bytes([d[2], d[3]]);
            let t = text(&d[4..d.len().min(68)]);
            (code as i64, format!("{t} (about message 0x{about:04X})"))
        } else {
            (
                -1,
                format!(
                    "MGMSG_HW_RESPONSE (params {:02x} {:02x}): the device reports a fault",
                    msg.param1, msg.param2
                ),
            )
        };
        DeviceError::Controller {
            device: self.port.device.clone(),
            command: command.to_string(),
            code,
            message,
        }
    }
}

/// Thorlabs APT devices: three KPZ101 piezo cubes (the stage) and a KPA101 position aligner (the QPD). (listed in `instrument::registry`).
/// Three Thorlabs KPZ101 piezo cubes over APT, one per axis: a `[stage]` backend.
pub const KPZ101: crate::instrument::family::Backend = crate::instrument::family::Backend("kpz101");

/// Thorlabs KPA101/TPA101 position aligner over APT: a `[qpd]` backend.
pub const KPA101: crate::instrument::family::Backend = crate::instrument::family::Backend("kpa101");

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn short_header_bytes() {
        // MGMSG_MOD_SET_CHANENABLESTATE, channel 1, enable: 10 02 01 01 50 01
        let m = Message::short(id::MOD_SET_CHANENABLESTATE, CHAN1, 0x01);
        assert_eq!(m.encode(), vec![0x10, 0x02, 0x01, 0x01, 0x50, 0x01]);
        assert_eq!(parse(&m.encode(), USB_UNIT), Parsed::Message(m, 6));
    }

    #[test]
    fn long_header_bytes_and_round_trip() {
        // MGMSG_PZ_SET_OUTPUTPOS, channel 1, position 0x3fff: 46 06 04 00 d0 01 01 00 ff 3f
        let m = Message::long(id::PZ_SET_OUTPUTPOS, vec![0x01, 0x00, 0xff, 0x3f]);
        let b = m.encode();
        assert_eq!(
            b,
            vec![0x46, 0x06, 0x04, 0x00, 0xd0, 0x01, 0x01, 0x00, 0xff, 0x3f]
        );
        assert_eq!(parse(&b, USB_UNIT), Parsed::Message(m.clone(), 10));
        // incomplete until the last data byte is there
        assert_eq!(parse(&b[..9], USB_UNIT), Parsed::Incomplete);
        assert_eq!(parse(&b[..5], USB_UNIT), Parsed::Incomplete);
        // the reply direction: dest 0x81, source 0x50
        let r = m.reply();
        let rb = r.encode();
        assert_eq!(&rb[..6], &[0x46, 0x06, 0x04, 0x00, 0x81, 0x50]);
        assert_eq!(parse(&rb, HOST), Parsed::Message(r, 10));
        // addressed wrongly for this end: invalid
        assert!(matches!(parse(&rb, USB_UNIT), Parsed::Invalid(_)));
    }

    #[test]
    fn overlong_and_misaddressed_headers_are_invalid() {
        let b = [0x72, 0x08, 0x00, 0x10, 0x81, 0x50]; // 4096 data bytes announced
        match parse(&b, HOST) {
            Parsed::Invalid(why) => assert!(why.contains("4096 data bytes"), "{why}"),
            other => panic!("{other:?}"),
        }
        let b = [0x06, 0x00, 0x00, 0x00, 0x23, 0x50];
        assert!(matches!(parse(&b, HOST), Parsed::Invalid(_)));
    }

    #[test]
    fn hw_info_round_trip() {
        let d = HwInfo::encode(29_000_123, "KPZ101", 96, (2, 1, 4), "piezo cube", 1);
        let i = HwInfo::decode(&d).unwrap();
        assert_eq!(i.serial, 29_000_123);
        assert_eq!(i.model, "KPZ101");
        assert_eq!(i.firmware, "2.1.4");
        assert_eq!(i.notes, "piezo cube");
        assert_eq!(i.channels, 1);
        assert!(HwInfo::decode(&d[..83]).is_none());
    }
}
