//! Thorlabs APT emulators: a KPA101 position aligner and KPZ101 piezo cubes, each on its own
//! pseudo-terminal, written from Thorlabs' "APT Communications Protocol" document (message ids,
//! packet layouts, scalings): set messages are not answered, requests get their `GET_…`, and an
//! unknown message id is ignored (no reply), as the document says the units do.
//!
//! Faults ([`Faults`]): `silent` (never answers), `garble_replies` (the next n replies have
//! their destination and source bytes replaced by 0xFF: a header no host accepts),
//! `unplug_after`, `error_next` (the next request is answered with `MGMSG_HW_RICHRESPONSE`
//! carrying that code), `settle_s` (KPZ101: slow settling), `silent_after` (serve n more
//! messages, then go silent) and `apt_unsolicited` (send a message with an unknown id, 0x0999,
//! before each of the next n replies).

use crate::instrument::emulation::{
    lock, sleep_s, Emulator, Faults, Line, LinkModel, SharedPosition, SignalSource, LOG_CAP,
};
use crate::instrument::thorlabs::kpa101::{
    RawReading, MODE_CLOSED_LOOP, SUB_OPER_MODE, SUB_READINGS,
};
use crate::instrument::thorlabs::kpz101::{chan_word, CHAN_DISABLED, CHAN_ENABLED, MODE_OPEN_LOOP};
use crate::instrument::thorlabs::{id, parse, HwInfo, Message, Parsed, CHAN1, USB_UNIT};
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The id of the unsolicited message sent by the `apt_unsolicited` fault (not used by any
/// device bfpscope knows).
pub const UNKNOWN_ID: u16 = 0x0999;

/// What an emulated APT unit does with one message from the host.
trait AptDevice: Send + 'static {
    /// The replies (usually none or one).
    fn handle(&mut self, m: &Message, faults: &Faults) -> Vec<Message>;
}

fn info_reply(serial: u32, model: &str, hw_type: u16) -> Message {
    Message::long(
        id::HW_GET_INFO,
        HwInfo::encode(serial, model, hw_type, (1, 0, 3), "bfpscope emulator", 1),
    )
    .reply()
}

/// KPA101 emulator settings.
#[derive(Debug, Clone, PartialEq)]
pub struct KpaEmulatorConfig {
    pub serial: u32,
    /// Sum with no sample, V (the detector's total signal: Sum = sum_v · (1 + Sz)).
    pub sum_v: f64,
    /// Operating mode at power-on (the driver must set monitor mode, 1).
    pub mode_at_power_on: u16,
    /// The USB-serial link modelled (APT: 115200 baud); default the pty's full speed
    /// (`bfpscope emulate` models the real one).
    pub link: LinkModel,
    /// White noise of the detector's outputs, V rms per reading, on XDiff, YDiff and Sum each
    /// before the ADC (0: none; the ADC's count of 0.3 mV then quantises a noiseless signal,
    /// and averaging readings cannot resolve below it).
    pub noise_v: f64,
    /// Seed of the noise.
    pub seed: u64,
}

impl Default for KpaEmulatorConfig {
    fn default() -> Self {
        Self {
            serial: 69_000_001,
            sum_v: 5.0,
            mode_at_power_on: MODE_CLOSED_LOOP,
            link: LinkModel::FULL_SPEED,
            noise_v: 0.0,
            seed: 1,
        }
    }
}

struct Kpa<S: SignalSource> {
    cfg: KpaEmulatorConfig,
    mode: u16,
    position: SharedPosition,
    source: S,
    rng: rand_chacha::ChaCha8Rng,
}

impl<S: SignalSource> Kpa<S> {
    /// The document's scaling: XDiff, YDiff ±10 V over ±32767, Sum 0–10 V over 0–65535.
    /// Signal → volts: Sum = sum_v·(1 + Sz), XDiff = Sx·Sum, YDiff = Sy·Sum, each plus the
    /// detector's noise (`noise_v`).
    fn reading(&mut self) -> RawReading {
        use rand::Rng;
        let p = *lock(&self.position);
        let [sx, sy, sz] = (self.source)(p);
        let sum = self.cfg.sum_v * (1.0 + sz);
        let mut noise = [0.0; 3];
        if self.cfg.noise_v > 0.0 {
            for v in noise.iter_mut() {
                *v = self.cfg.noise_v * self.rng.sample::<f64, _>(rand_distr::StandardNormal);
            }
        }
        let diff = |v: f64| (v / 10.0 * 32767.0).round().clamp(-32768.0, 32767.0) as i16;
        RawReading {
            xdiff: diff(sx * sum + noise[0]),
            ydiff: diff(sy * sum + noise[1]),
            sum: ((sum + noise[2]) / 10.0 * 65535.0)
                .round()
                .clamp(0.0, 65535.0) as u16,
            xpos: 0,
            ypos: 0,
        }
    }
}

impl<S: SignalSource> AptDevice for Kpa<S> {
    fn handle(&mut self, m: &Message, _faults: &Faults) -> Vec<Message> {
        match m.id {
            id::HW_REQ_INFO => vec![info_reply(self.cfg.serial, "KPA101", 73)],
            id::QUAD_SET_PARAMS => {
                let d = m.bytes();
                if d.len() == 4 && d[0] == SUB_OPER_MODE && d[1] == 0 {
                    let mode = u16::from_le_bytes([d[2], d[3]]);
                    if (1..=4).contains(&mode) {
                        self.mode = mode;
                    }
                }
                vec![]
            }
            id::QUAD_REQ_PARAMS => match m.param1 {
                SUB_READINGS => {
                    vec![Message::long(id::QUAD_GET_PARAMS, self.reading().encode()).reply()]
                }
                SUB_OPER_MODE => {
                    let mut d = (SUB_OPER_MODE as u16).to_le_bytes().to_vec();
                    d.extend_from_slice(&self.mode.to_le_bytes());
                    vec![Message::long(id::QUAD_GET_PARAMS, d).reply()]
                }
                _ => vec![],
            },
            id::QUAD_REQ_STATUSUPDATE => {
                // XDiff, YDiff, Sum, XPos, YPos, status bits (u32)
                let mut d = self.reading().encode()[2..].to_vec();
                d.extend_from_slice(&0u32.to_le_bytes());
                vec![Message::long(id::QUAD_GET_STATUSUPDATE, d).reply()]
            }
            // HW_NO_FLASH_PROGRAMMING, HW_START/STOP_UPDATEMSGS, MOD_IDENTIFY and unknown ids:
            // no reply
            _ => vec![],
        }
    }
}

/// KPZ101 emulator settings (one cube).
#[derive(Debug, Clone, PartialEq)]
pub struct KpzEmulatorConfig {
    pub serial: u32,
    /// Which coordinate of the shared position this cube drives (0 = x, 1 = y, 2 = z).
    pub axis: usize,
    /// Maximum travel, µm (reported in units of 100 nm).
    pub travel_um: f64,
    /// Position counts for 100 % of the travel (the document: 32767).
    pub full_scale: u16,
    /// Time to reach a new demand, s (linear ramp).
    pub settle_s: f64,
    /// The strain gauge is zeroed at power-on (status bit 0x10, "zeroed").
    pub zeroed_at_power_on: bool,
    /// Offset of the strain-gauge reading until it is zeroed, µm: the position read back
    /// (`MGMSG_PZ_GET_OUTPUTPOS`) is the actuator's position plus this, and the closed loop
    /// holds the *reading* on the demand, so the actuator sits this much short of it.
    pub gauge_offset_um: f64,
    /// Time `MGMSG_PZ_SET_ZERO` takes, s: the output goes to 0 V (the actuator ramps to its
    /// zero), status bit 0x20 "zeroing" is set meanwhile, then 0x10 "zeroed" and the offset is
    /// gone. Thorlabs' document gives no duration.
    pub zero_s: f64,
    /// The USB-serial link modelled (APT: 115200 baud); default the pty's full speed
    /// (`bfpscope emulate` models the real one).
    pub link: LinkModel,
}

impl Default for KpzEmulatorConfig {
    /// A cube as powered on: gauge not zeroed (no offset: set `gauge_offset_um` to model one),
    /// zeroing in 20 ms.
    fn default() -> Self {
        Self {
            serial: 29_000_001,
            axis: 0,
            travel_um: 20.0,
            full_scale: 32767,
            settle_s: 0.002,
            zeroed_at_power_on: false,
            gauge_offset_um: 0.0,
            zero_s: 0.02,
            link: LinkModel::FULL_SPEED,
        }
    }
}

/// `MGMSG_PZ_GET_PZSTATUSUPDATE` status bits (Thorlabs' APT document; the same in
/// `thorlabs_apt_protocol`'s parser): actuator connected, zeroed, zeroing, strain gauge
/// connected, closed loop, channel enabled.
pub mod pz_status {
    pub const CONNECTED: u32 = 0x0000_0001;
    pub const ZEROED: u32 = 0x0000_0010;
    pub const ZEROING: u32 = 0x0000_0020;
    pub const GAUGE_CONNECTED: u32 = 0x0000_0100;
    pub const CLOSED_LOOP: u32 = 0x0000_0400;
    pub const ENABLED: u32 = 0x8000_0000;
}

struct Kpz {
    cfg: KpzEmulatorConfig,
    mode: u8,
    enabled: bool,
    position: SharedPosition,
    /// Ramp: from, to (µm), start, duration.
    ramp: Option<(f64, f64, Instant, f64)>,
    zeroed: bool,
    /// Zeroing under way since this instant.
    zeroing: Option<Instant>,
    /// The gauge's offset now, µm (0 once zeroed).
    offset_um: f64,
}

impl Kpz {
    /// The actuator's position, µm (what the QPD sees); ends a zeroing that is complete.
    fn now_um(&mut self) -> f64 {
        if let Some(t0) = self.zeroing {
            if t0.elapsed().as_secs_f64() >= self.cfg.zero_s {
                self.zeroing = None;
                self.zeroed = true;
                self.offset_um = 0.0;
            }
        }
        if let Some((from, to, t0, dur)) = self.ramp {
            let f = if dur <= 0.0 {
                1.0
            } else {
                (t0.elapsed().as_secs_f64() / dur).min(1.0)
            };
            let p = from + (to - from) * f;
            lock(&self.position)[self.cfg.axis] = p;
            if f >= 1.0 {
                self.ramp = None;
            }
        }
        lock(&self.position)[self.cfg.axis]
    }

    /// What the strain gauge reads for the actuator at `um`, µm.
    fn reading_um(&self, um: f64) -> f64 {
        um + self.offset_um
    }

    fn counts(&self, um: f64) -> u16 {
        (um / self.cfg.travel_um * self.cfg.full_scale as f64)
            .round()
            .clamp(0.0, self.cfg.full_scale as f64) as u16
    }
}

impl AptDevice for Kpz {
    fn handle(&mut self, m: &Message, faults: &Faults) -> Vec<Message> {
        let here = self.now_um();
        match m.id {
            id::HW_REQ_INFO => vec![info_reply(self.cfg.serial, "KPZ101", 29)],
            id::MOD_SET_CHANENABLESTATE if m.param1 == CHAN1 => {
                self.enabled = m.param2 == CHAN_ENABLED;
                vec![]
            }
            id::MOD_REQ_CHANENABLESTATE => vec![Message::short(
                id::MOD_GET_CHANENABLESTATE,
                CHAN1,
                if self.enabled {
                    CHAN_ENABLED
                } else {
                    CHAN_DISABLED
                },
            )
            .reply()],
            id::PZ_SET_POSCONTROLMODE if m.param1 == CHAN1 && (1..=4).contains(&m.param2) => {
                self.mode = m.param2;
                vec![]
            }
            id::PZ_REQ_POSCONTROLMODE => {
                vec![Message::short(id::PZ_GET_POSCONTROLMODE, CHAN1, self.mode).reply()]
            }
            id::PZ_REQ_MAXTRAVEL => vec![Message::long(
                id::PZ_GET_MAXTRAVEL,
                chan_word((self.cfg.travel_um * 10.0).round() as u16),
            )
            .reply()],
            id::PZ_SET_OUTPUTPOS => {
                let d = m.bytes();
                // the document: the position is set in closed-loop mode only
                // (and not while zeroing: the output is held at 0 V)
                if d.len() == 4
                    && self.enabled
                    && self.mode.is_multiple_of(2)
                    && self.zeroing.is_none()
                {
                    let c = u16::from_le_bytes([d[2], d[3]]).min(self.cfg.full_scale);
                    let demand = c as f64 / self.cfg.full_scale as f64 * self.cfg.travel_um;
                    // the loop holds the gauge's reading on the demand
                    let to = (demand - self.offset_um).clamp(0.0, self.cfg.travel_um);
                    let dur = faults.settle_s.unwrap_or(self.cfg.settle_s);
                    self.ramp = Some((here, to, Instant::now(), dur));
                }
                vec![]
            }
            // the document: 0 V to the actuator, then the reading there becomes the zero
            id::PZ_SET_ZERO if m.param1 == CHAN1 => {
                self.zeroing = Some(Instant::now());
                self.zeroed = false;
                self.ramp = Some((here, 0.0, Instant::now(), self.cfg.zero_s));
                vec![]
            }
            id::PZ_REQ_OUTPUTPOS => {
                let r = self.reading_um(here);
                vec![Message::long(id::PZ_GET_OUTPUTPOS, chan_word(self.counts(r))).reply()]
            }
            id::PZ_REQ_PZSTATUSUPDATE => {
                let mut d = (CHAN1 as u16).to_le_bytes().to_vec();
                let volts = (here / self.cfg.travel_um * 32767.0).round() as i16;
                d.extend_from_slice(&volts.to_le_bytes());
                let r = self.reading_um(here);
                d.extend_from_slice(&(self.counts(r) as i16).to_le_bytes());
                let mut bits: u32 = pz_status::CONNECTED | pz_status::GAUGE_CONNECTED;
                if self.mode.is_multiple_of(2) {
                    bits |= pz_status::CLOSED_LOOP;
                }
                if self.enabled {
                    bits |= pz_status::ENABLED;
                }
                if self.zeroed {
                    bits |= pz_status::ZEROED;
                }
                if self.zeroing.is_some() {
                    bits |= pz_status::ZEROING;
                }
                d.extend_from_slice(&bits.to_le_bytes());
                vec![Message::long(id::PZ_GET_PZSTATUSUPDATE, d).reply()]
            }
            _ => vec![],
        }
    }
}

/// Start a KPA101 emulator reading `source` at the shared stage position.
pub fn start_kpa101_emulator(
    cfg: KpaEmulatorConfig,
    position: SharedPosition,
    source: impl SignalSource,
) -> std::io::Result<Emulator> {
    use rand::SeedableRng;
    let mode = cfg.mode_at_power_on;
    let link = cfg.link;
    let rng = rand_chacha::ChaCha8Rng::seed_from_u64(cfg.seed);
    spawn_apt(
        "kpa101",
        Kpa {
            cfg,
            mode,
            position: position.clone(),
            source,
            rng,
        },
        position,
        link,
    )
}

/// Start one KPZ101 emulator driving coordinate `cfg.axis` of the shared position. At
/// power-on: open loop, channel disabled.
pub fn start_kpz101_emulator(
    cfg: KpzEmulatorConfig,
    position: SharedPosition,
) -> std::io::Result<Emulator> {
    let link = cfg.link;
    spawn_apt(
        "kpz101",
        Kpz {
            mode: MODE_OPEN_LOOP,
            enabled: false,
            position: position.clone(),
            ramp: None,
            zeroed: cfg.zeroed_at_power_on,
            zeroing: None,
            offset_um: if cfg.zeroed_at_power_on {
                0.0
            } else {
                cfg.gauge_offset_um
            },
            cfg,
        },
        position,
        link,
    )
}

/// Three KPZ101 emulators (x, y, z; serials 29000001…3, `travel_um` each) sharing `position`.
pub fn start_kpz101_stage(
    travel_um: [f64; 3],
    position: SharedPosition,
) -> std::io::Result<[Emulator; 3]> {
    start_kpz101_stage_on(travel_um, position, LinkModel::FULL_SPEED)
}

/// As [`start_kpz101_stage`], each cube's USB-serial link modelled by `link`.
pub fn start_kpz101_stage_on(
    travel_um: [f64; 3],
    position: SharedPosition,
    link: LinkModel,
) -> std::io::Result<[Emulator; 3]> {
    let one = |axis: usize| {
        start_kpz101_emulator(
            KpzEmulatorConfig {
                serial: 29_000_001 + axis as u32,
                axis,
                travel_um: travel_um[axis],
                link,
                ..KpzEmulatorConfig::default()
            },
            position.clone(),
        )
    };
    Ok([one(0)?, one(1)?, one(2)?])
}

fn spawn_apt(
    kind: &'static str,
    device: impl AptDevice,
    position: SharedPosition,
    link: LinkModel,
) -> std::io::Result<Emulator> {
    let (line, path) = crate::instrument::emulation::pty_line()?;
    let faults = Arc::new(Mutex::new(Faults::default()));
    let f = faults.clone();
    crate::instrument::emulation::launch(kind, faults, position, path, move |h| {
        AptServe {
            line,
            device,
            link,
            faults: f,
            log: h.log,
            stop: h.stop,
            finished: h.finished,
        }
        .run()
    })
}

struct AptServe<D: AptDevice> {
    line: Line,
    device: D,
    link: LinkModel,
    faults: Arc<Mutex<Faults>>,
    log: Arc<Mutex<VecDeque<String>>>,
    stop: Arc<AtomicBool>,
    finished: Arc<AtomicBool>,
}

impl<D: AptDevice> AptServe<D> {
    fn run(mut self) {
        let mut buf: Vec<u8> = Vec::new();
        let mut chunk = [0u8; 512];
        'serve: while !self.stop.load(Ordering::SeqCst)
            && lock(&self.faults).unplug_after != Some(0)
        {
            let mut new_session = false;
            match self.line.read(&mut chunk, &mut new_session) {
                Ok(0) => std::thread::sleep(Duration::from_millis(2)),
                Ok(n) => buf.extend_from_slice(&chunk[..n]),
                Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                Err(_) => std::thread::sleep(Duration::from_millis(5)),
            }
            loop {
                match parse(&buf, USB_UNIT) {
                    Parsed::Message(m, used) => {
                        buf.drain(..used);
                        if !self.serve(&m) {
                            std::thread::sleep(Duration::from_millis(50));
                            break 'serve;
                        }
                    }
                    // line noise: drop a byte and look for a header again
                    Parsed::Invalid(_) => {
                        buf.remove(0);
                    }
                    Parsed::Incomplete => break,
                }
            }
        }
        self.finished.store(true, Ordering::SeqCst);
    }

    /// Serve one message; false when the emulator unplugs itself.
    fn serve(&mut self, m: &Message) -> bool {
        // the message's bytes on the modelled wire
        sleep_s(self.link.wire_s(m.encode().len()));
        {
            let mut log = lock(&self.log);
            if log.len() >= LOG_CAP {
                log.pop_front();
            }
            log.push_back(m.describe());
        }
        let last = {
            let mut g = lock(&self.faults);
            match g.silent_after {
                Some(0) => g.silent = true,
                Some(n) => g.silent_after = Some(n - 1),
                None => {}
            }
            match g.unplug_after {
                Some(n) => {
                    g.unplug_after = Some(n.saturating_sub(1));
                    n <= 1
                }
                None => false,
            }
        };
        let f = lock(&self.faults).clone();
        let mut replies = self.device.handle(m, &f);
        if !replies.is_empty() {
            if let Some(code) = lock(&self.faults).error_next.take() {
                let mut d = m.id.to_le_bytes().to_vec();
                d.extend_from_slice(&(code as u16).to_le_bytes());
                let mut text = format!("emulated fault {code}").into_bytes();
                text.resize(64, 0);
                d.extend_from_slice(&text);
                replies = vec![Message::long(id::HW_RICHRESPONSE, d).reply()];
            }
        }
        if f.silent {
            return !last;
        }
        for r in replies {
            let mut out = Vec::new();
            {
                let mut g = lock(&self.faults);
                if g.apt_unsolicited > 0 {
                    g.apt_unsolicited -= 1;
                    out.extend(Message::long(UNKNOWN_ID, vec![1, 2, 3, 4]).reply().encode());
                }
            }
            let mut b = r.encode();
            {
                let mut g = lock(&self.faults);
                if g.garble_replies > 0 {
                    g.garble_replies -= 1;
                    b[4] = 0xFF;
                    b[5] = 0xFF;
                }
            }
            out.extend(b);
            // the unit's reply latency and the reply's bytes on the wire
            sleep_s(self.link.latency.as_secs_f64() + self.link.wire_s(out.len()));
            let _ = self.line.write_all(&out);
        }
        !last
    }
}
