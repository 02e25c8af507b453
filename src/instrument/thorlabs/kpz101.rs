//! Thorlabs KPZ101 piezo K-Cube: one closed-loop axis with a strain-gauge actuator; three of
//! them make one x, y, z [`Stage`] ([`Kpz101Stage`]).
//!
//! Position: `MGMSG_PZ_SET_OUTPUTPOS` / `REQ` / `GET` carry channel (u16) and position (u16) in
//! counts of the actuator's travel: 0 … `full_scale` is 0 … 100 % of the maximum travel
//! (`MGMSG_PZ_GET_MAXTRAVEL`, in units of 100 nm, or `stage.travel_um`). Positions in µm run
//! from 0 at the actuator's zero to the travel.
//!
//! At connect nothing is switched: `MGMSG_HW_NO_FLASH_PROGRAMMING`, `MGMSG_HW_STOP_UPDATEMSGS`,
//! `MGMSG_HW_REQ_INFO` (must be a KPZ101/TPZ001), the channel enable state, the position
//! control mode, the maximum travel and the position are read. [`Stage::enable`] (after the
//! soft limits were checked) switches the loop closed (`MGMSG_PZ_SET_POSCONTROLMODE` 2), sets
//! the position demand to the position just read (so closing the loop moves nothing), enables
//! the channel (`MGMSG_MOD_SET_CHANENABLESTATE` 1) and reads both states back.
//!
//! **Strain gauge.** Closed-loop positions are the strain gauge's readings, which carry an
//! offset until the gauge is zeroed (`MGMSG_PZ_SET_ZERO`; status bits 0x20 "zeroing", then
//! 0x10 "zeroed" in `MGMSG_PZ_GET_PZSTATUSUPDATE`). The bit is read at connect
//! ([`Kpz101::zeroed_at_connect`]); `zero_at_connect` zeroes before the loop is closed, and
//! [`GaugeZero::zero_gauge`](crate::instrument::GaugeZero::zero_gauge) on request. Zeroing drives the actuator to 0 V, its zero.
//!
//! **Stop.** A piezo cube has no motion to cancel: it drives the actuator to the demand within
//! milliseconds. `stop` asks each cube for its position and makes that the demand
//! (`MGMSG_PZ_SET_OUTPUTPOS` with the position read; the last commanded target when the cube
//! does not answer), so the actuator holds where it is. It does not zero the output voltage
//! nor disable the channel: both drop the actuator to its zero, a move of up to the whole
//! travel.

use super::{id, open_apt_serial, AptLink, HwInfo, Message, CHAN1};
use crate::instrument::device::all_then_first_error;
use crate::instrument::link::Transport;
use crate::instrument::{DeviceError, Pos, Stage};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// Position control modes (`MGMSG_PZ_SET_POSCONTROLMODE`).
pub const MODE_OPEN_LOOP: u8 = 1;
pub const MODE_CLOSED_LOOP: u8 = 2;
pub const MODE_OPEN_LOOP_SMOOTH: u8 = 3;
pub const MODE_CLOSED_LOOP_SMOOTH: u8 = 4;
/// Channel states (`MGMSG_MOD_SET_CHANENABLESTATE`).
pub const CHAN_ENABLED: u8 = 1;
pub const CHAN_DISABLED: u8 = 2;
/// Counts for 100 % of the travel per Thorlabs' document (the default of `full_scale`).
pub const FULL_SCALE_DOC: u16 = 32767;
/// `MGMSG_PZ_GET_PZSTATUSUPDATE` status bits (Thorlabs' APT document): the strain gauge has
/// been zeroed, is being zeroed.
pub const STATUS_ZEROED: u32 = 0x0000_0010;
pub const STATUS_ZEROING: u32 = 0x0000_0020;

/// Driver settings for one cube (`[stage]` with `backend = "kpz101"`).
#[derive(Debug, Clone, PartialEq)]
pub struct KpzOptions {
    pub timeout: Duration,
    /// Longest wait for the position to reach the target after a move.
    pub on_target_timeout: Duration,
    pub poll_interval: Duration,
    /// On target when within this distance, µm.
    pub tolerance_um: f64,
    /// Travel in µm instead of what `MGMSG_PZ_REQ_MAXTRAVEL` reports.
    pub travel_um: Option<f64>,
    /// Position counts for 100 % of the travel (document: 32767; some firmware 65535).
    pub full_scale: u16,
    pub rtscts: bool,
    /// Zero the strain gauge at connect (`MGMSG_PZ_SET_ZERO`, before the loop is closed)
    /// when its status says it is not zeroed.
    pub zero_at_connect: bool,
    /// Longest wait for the "zeroed" status bit after `MGMSG_PZ_SET_ZERO`.
    pub zero_timeout: Duration,
}

impl Default for KpzOptions {
    fn default() -> Self {
        Self {
            timeout: Duration::from_millis(1000),
            on_target_timeout: Duration::from_millis(5000),
            poll_interval: Duration::from_millis(5),
            tolerance_um: 0.05,
            travel_um: None,
            full_scale: FULL_SCALE_DOC,
            rtscts: true,
            zero_at_connect: false,
            zero_timeout: Duration::from_millis(60_000),
        }
    }
}

/// The `[chan u16, value u16]` packet of the PZ position and travel messages.
pub fn chan_word(value: u16) -> Vec<u8> {
    let mut d = (CHAN1 as u16).to_le_bytes().to_vec();
    d.extend_from_slice(&value.to_le_bytes());
    d
}

/// One KPZ101 driving one axis.
pub struct Kpz101 {
    link: AptLink,
    opts: KpzOptions,
    info: HwInfo,
    travel_um: f64,
    /// Travel as the cube reported it (µm), before any override.
    reported_travel_um: f64,
    enabled_at_connect: bool,
    mode_at_connect: u8,
    /// The gauge's "zeroed" status bit at connect, and now (after a zeroing).
    zeroed_at_connect: bool,
    zeroed: bool,
    target_um: f64,
    port: String,
}

impl Kpz101 {
    /// Open the port and connect (reads only).
    pub fn open(port: &str, axis: &str, opts: KpzOptions) -> Result<Self, DeviceError> {
        let device = format!("Thorlabs KPZ101 ({axis}) on {port}");
        let io = if opts.rtscts {
            open_apt_serial(&device, port, opts.timeout)?
        } else {
            crate::instrument::link::open_serial(&device, port, 115_200, opts.timeout)?
        };
        Self::connect(io, port, axis, opts)
    }

    pub fn connect(
        io: Box<dyn Transport>,
        port: &str,
        axis: &str,
        opts: KpzOptions,
    ) -> Result<Self, DeviceError> {
        let mut link = AptLink::new(
            io,
            format!("Thorlabs KPZ101 ({axis}) on {port}"),
            opts.timeout,
        );
        let info = link.identify()?;
        let model = info.model.to_ascii_uppercase();
        if !(model.starts_with("KPZ") || model.starts_with("TPZ")) {
            return Err(DeviceError::Other {
                device: link.device().to_string(),
                detail: format!(
                    "`{}` answered model {:?} (serial {}): not a piezo cube (KPZ101, TPZ001); check \
                     stage.ports.{axis}",
                    Message::short(id::HW_REQ_INFO, 0, 0).describe(),
                    info.model,
                    info.serial
                ),
            });
        }
        link.set_device(format!(
            "Thorlabs {} #{} ({axis}) on {port}",
            info.model, info.serial
        ));
        let mut a = Self {
            link,
            opts,
            info,
            travel_um: 0.0,
            reported_travel_um: 0.0,
            enabled_at_connect: false,
            mode_at_connect: 0,
            zeroed_at_connect: false,
            zeroed: false,
            target_um: 0.0,
            port: port.to_string(),
        };
        a.enabled_at_connect = a.chan_enabled()?;
        a.mode_at_connect = a.control_mode()?;
        a.zeroed_at_connect = a.status_bits()? & STATUS_ZEROED != 0;
        a.zeroed = a.zeroed_at_connect;
        let req = Message::short(id::PZ_REQ_MAXTRAVEL, CHAN1, 0);
        let r = a.link.request(&req, id::PZ_GET_MAXTRAVEL)?;
        let t = a.chan_value(&req, &r)?;
        a.reported_travel_um = t as f64 * 0.1;
        a.travel_um = match a.opts.travel_um {
            Some(t) => t,
            None if t > 0 => a.reported_travel_um,
            None => {
                return Err(DeviceError::Other {
                    device: a.name(),
                    detail: format!(
                        "`{}` answered a maximum travel of 0: no strain-gauge actuator found (closed loop \
                         needs one); set stage.travel_um if the actuator has one",
                        req.describe()
                    ),
                })
            }
        };
        a.target_um = a.position_um()?;
        Ok(a)
    }

    pub fn name(&self) -> String {
        self.link.device().to_string()
    }

    fn chan_value(&self, req: &Message, r: &Message) -> Result<u16, DeviceError> {
        let d = r.bytes();
        if d.len() != 4 || u16::from_le_bytes([d[0], d[1]]) != CHAN1 as u16 {
            return Err(DeviceError::Garbled {
                device: self.name(),
                command: req.describe(),
                reply: format!("{} (expected channel 1 and a 16-bit value)", r.describe()),
            });
        }
        Ok(u16::from_le_bytes([d[2], d[3]]))
    }

    /// `MGMSG_MOD_REQ_CHANENABLESTATE`.
    pub fn chan_enabled(&mut self) -> Result<bool, DeviceError> {
        let req = Message::short(id::MOD_REQ_CHANENABLESTATE, CHAN1, 0);
        let r = self.link.request(&req, id::MOD_GET_CHANENABLESTATE)?;
        Ok(r.param2 == CHAN_ENABLED)
    }

    /// `MGMSG_PZ_REQ_POSCONTROLMODE`.
    pub fn control_mode(&mut self) -> Result<u8, DeviceError> {
        let req = Message::short(id::PZ_REQ_POSCONTROLMODE, CHAN1, 0);
        let r = self.link.request(&req, id::PZ_GET_POSCONTROLMODE)?;
        Ok(r.param2)
    }

    /// The status bits of `MGMSG_PZ_REQ_PZSTATUSUPDATE` (reply: channel u16, output voltage
    /// i16, position i16, status u32).
    pub fn status_bits(&mut self) -> Result<u32, DeviceError> {
        let req = Message::short(id::PZ_REQ_PZSTATUSUPDATE, CHAN1, 0);
        let r = self.link.request(&req, id::PZ_GET_PZSTATUSUPDATE)?;
        let d = r.bytes();
        if d.len() < 10 || u16::from_le_bytes([d[0], d[1]]) != CHAN1 as u16 {
            return Err(DeviceError::Garbled {
                device: self.name(),
                command: req.describe(),
                reply: format!(
                    "{} (expected channel 1, voltage, position and 32 status bits)",
                    r.describe()
                ),
            });
        }
        Ok(u32::from_le_bytes([d[6], d[7], d[8], d[9]]))
    }

    /// Zero the strain gauge: `MGMSG_PZ_SET_ZERO` (Thorlabs: 0 V to the actuator, then the
    /// position read there is the zero of all later readings), then the status polled every
    /// `poll_interval` until "zeroed" (0x10) is set and "zeroing" (0x20) clear, at most
    /// `timeout`. The actuator ends at its zero; the demand is set to the position read
    /// there, so it holds. A timeout holds the actuator where it is and names the last status.
    pub fn zero(&mut self, timeout: Duration) -> Result<(), DeviceError> {
        let m = Message::short(id::PZ_SET_ZERO, CHAN1, 0);
        self.link.send(&m)?;
        self.zeroed = false;
        let t0 = Instant::now();
        loop {
            let bits = self.status_bits().map_err(|e| {
                e.during(&format!(
                    "MGMSG_PZ_REQ_PZSTATUSUPDATE (after `{}`)",
                    m.describe()
                ))
            })?;
            if bits & STATUS_ZEROED != 0 && bits & STATUS_ZEROING == 0 {
                break;
            }
            if t0.elapsed() >= timeout {
                let _ = self.hold();
                return Err(DeviceError::Other {
                    device: self.name(),
                    detail: format!(
                        "strain gauge not zeroed within {} ms after `{}`: last status bits 0x{bits:08x} \
                         (zeroing {}, zeroed {}); the actuator was told to hold where it is",
                        timeout.as_millis(),
                        m.describe(),
                        u8::from(bits & STATUS_ZEROING != 0),
                        u8::from(bits & STATUS_ZEROED != 0)
                    ),
                });
            }
            std::thread::sleep(self.opts.poll_interval);
        }
        self.zeroed = true;
        self.target_um = self.position_um()?;
        if self.control_mode()? % 2 == 0 && self.chan_enabled()? {
            self.set_target(self.target_um)?;
        }
        Ok(())
    }

    /// The gauge's "zeroed" bit at connect.
    pub fn zeroed_at_connect(&self) -> bool {
        self.zeroed_at_connect
    }

    /// Whether the gauge is zeroed (at connect, or by [`Self::zero`] since).
    pub fn zeroed(&self) -> bool {
        self.zeroed
    }

    /// The position (µm from the actuator's zero), `MGMSG_PZ_REQ_OUTPUTPOS`.
    pub fn position_um(&mut self) -> Result<f64, DeviceError> {
        let req = Message::short(id::PZ_REQ_OUTPUTPOS, CHAN1, 0);
        let r = self.link.request(&req, id::PZ_GET_OUTPUTPOS)?;
        let c = self.chan_value(&req, &r)?;
        Ok(c as f64 / self.opts.full_scale as f64 * self.travel_um)
    }

    /// Counts for `um`; an error when it cannot be encoded (outside 0 … travel).
    pub fn counts(&self, um: f64) -> Result<u16, DeviceError> {
        let c = (um / self.travel_um * self.opts.full_scale as f64).round();
        if !(c >= 0.0 && c <= self.opts.full_scale as f64) {
            return Err(DeviceError::Other {
                device: self.name(),
                detail: format!(
                    "target {um} µm is outside the actuator's travel 0–{} µm: it cannot be sent as \
                     MGMSG_PZ_SET_OUTPUTPOS",
                    self.travel_um
                ),
            });
        }
        Ok(c as u16)
    }

    /// Send the position demand (no reply: set messages are not acknowledged).
    pub fn set_target(&mut self, um: f64) -> Result<Message, DeviceError> {
        let m = Message::long(id::PZ_SET_OUTPUTPOS, chan_word(self.counts(um)?));
        self.link.send(&m)?;
        self.target_um = um;
        Ok(m)
    }

    /// Closed loop, demand = the position now, channel enabled; both read back. With
    /// `zero_at_connect`, a gauge not zeroed is zeroed first ([`Self::zero`]).
    pub fn enable(&mut self) -> Result<(), DeviceError> {
        if self.opts.zero_at_connect && !self.zeroed {
            self.zero(self.opts.zero_timeout)?;
        }
        let here = self.position_um()?;
        self.link.send(&Message::short(
            id::PZ_SET_POSCONTROLMODE,
            CHAN1,
            MODE_CLOSED_LOOP,
        ))?;
        self.set_target(here)?;
        self.link.send(&Message::short(
            id::MOD_SET_CHANENABLESTATE,
            CHAN1,
            CHAN_ENABLED,
        ))?;
        let mode = self.control_mode()?;
        let on = self.chan_enabled()?;
        if mode != MODE_CLOSED_LOOP || !on {
            return Err(DeviceError::Other {
                device: self.name(),
                detail: format!(
                    "closed loop and channel enable were sent, but the cube reports mode {mode} (2 = closed \
                     loop) and channel {} : is a strain-gauge actuator connected?",
                    if on { "enabled" } else { "disabled" }
                ),
            });
        }
        Ok(())
    }

    /// Hold where the actuator is (see the module notes); the message sent.
    pub fn hold(&mut self) -> Result<Message, DeviceError> {
        let saved = self.link.timeout;
        self.link.timeout = saved.min(Duration::from_millis(200));
        let here = self.position_um();
        self.link.timeout = saved;
        let at = match here {
            Ok(p) => p.clamp(0.0, self.travel_um),
            Err(_) => self.target_um,
        };
        self.set_target(at)
    }

    pub fn travel_um(&self) -> f64 {
        self.travel_um
    }

    pub fn reported_travel_um(&self) -> f64 {
        self.reported_travel_um
    }

    pub fn info(&self) -> &HwInfo {
        &self.info
    }

    pub fn port(&self) -> &str {
        &self.port
    }

    /// What each message cost on this cube's link since the last call.
    pub fn take_link_costs(&mut self) -> crate::instrument::link::LinkCosts {
        self.link.take_costs()
    }

    /// The link's reply latency beyond the bytes' wire time, s (see [`AptLink::latency_s`]).
    pub fn latency_s(&self) -> Option<f64> {
        self.link.latency_s()
    }

    pub fn enabled_at_connect(&self) -> bool {
        self.enabled_at_connect
    }

    pub fn mode_at_connect(&self) -> u8 {
        self.mode_at_connect
    }
}

/// Three KPZ101 cubes as the x, y, z stage.
pub struct Kpz101Stage {
    axes: [Kpz101; 3],
    opts: KpzOptions,
    /// Wall time of a move (targets sent to on target), running mean, for the ETA.
    move_time: crate::instrument::gcs::MeanTime,
}

const XYZ: [&str; 3] = ["x", "y", "z"];

impl Kpz101Stage {
    /// Open the three cubes (ports in x, y, z order). If one fails, the others are closed
    /// again untouched.
    /// `travel_um` overrides the travel each cube reports (x, y, z).
    pub fn open(
        ports: [&str; 3],
        opts: KpzOptions,
        travel_um: Option<[f64; 3]>,
    ) -> Result<Self, DeviceError> {
        let o = |i: usize| KpzOptions {
            travel_um: travel_um.map(|t| t[i]),
            ..opts.clone()
        };
        let x = Kpz101::open(ports[0], "x", o(0))?;
        let y = Kpz101::open(ports[1], "y", o(1))?;
        let z = Kpz101::open(ports[2], "z", o(2))?;
        Ok(Self {
            axes: [x, y, z],
            opts,
            move_time: Default::default(),
        })
    }

    /// What a point scan's step (one axis) costs before any move was measured, s (the first
    /// scan after connecting): `MGMSG_PZ_SET_OUTPUTPOS` written (10 bytes, never acknowledged),
    /// then `MGMSG_PZ_REQ_OUTPUTPOS` (6 bytes) answered by `MGMSG_PZ_GET_OUTPUTPOS` (10 bytes)
    /// twice — the first poll sees the actuator still on its way (the closed loop takes
    /// milliseconds), the second on target — with one poll interval between them; each reply
    /// costing the link's latency (the median over the connect's requests on the cubes) plus
    /// its bytes at APT's 115200 baud (10 bits per byte). Longer settling shows after the first
    /// row, when the engine revises the ETA from the measured cost. 0 before any reply.
    pub fn move_time_prior_s(&self) -> f64 {
        let lat: Vec<f64> = self.axes.iter().filter_map(|a| a.latency_s()).collect();
        if lat.is_empty() {
            return 0.0;
        }
        let lat = lat.iter().sum::<f64>() / lat.len() as f64;
        let wire = |bytes: f64| bytes / super::APT_BYTES_PER_S;
        wire(10.0) + 2.0 * (lat + wire(6.0 + 10.0)) + self.opts.poll_interval.as_secs_f64()
    }

    pub fn axes(&self) -> &[Kpz101; 3] {
        &self.axes
    }

    fn wait_on_target(
        &mut self,
        moved: &[(usize, String)],
        abort: Option<&AtomicBool>,
    ) -> Result<bool, DeviceError> {
        let deadline = Instant::now() + self.opts.on_target_timeout;
        for (i, cmd) in moved {
            let i = *i;
            loop {
                let p = self.axes[i]
                    .position_um()
                    .map_err(|e| e.during(&format!("MGMSG_PZ_REQ_OUTPUTPOS (after `{cmd}`)")))?;
                let t = self.axes[i].target_um;
                if (p - t).abs() <= self.opts.tolerance_um {
                    break;
                }
                if abort.is_some_and(|a| a.load(Ordering::SeqCst)) {
                    return Ok(false);
                }
                if Instant::now() >= deadline {
                    return Err(DeviceError::Other {
                        device: self.axes[i].name(),
                        detail: format!(
                            "not on target within {} ms after `{cmd}`: position {p:.4} µm, target {t:.4} µm \
                             (tolerance {} µm)",
                            self.opts.on_target_timeout.as_millis(),
                            self.opts.tolerance_um
                        ),
                    });
                }
                std::thread::sleep(self.opts.poll_interval);
            }
        }
        Ok(true)
    }

    fn do_move(&mut self, target: Pos, abort: Option<&AtomicBool>) -> Result<bool, DeviceError> {
        let t0 = Instant::now();
        let mut moved = Vec::new();
        for i in 0..3 {
            if target[i] != self.axes[i].target_um {
                let m = self.axes[i].set_target(target[i])?;
                moved.push((i, m.describe()));
            }
        }
        let r = self.wait_on_target(&moved, abort);
        if matches!(r, Ok(true)) && !moved.is_empty() {
            self.move_time.add(t0.elapsed().as_secs_f64());
        }
        r
    }
}

impl Stage for Kpz101Stage {
    fn name(&self) -> String {
        format!(
            "Thorlabs KPZ101 ×3 ({})",
            (0..3)
                .map(|i| format!(
                    "{} #{} on {}",
                    XYZ[i], self.axes[i].info.serial, self.axes[i].port
                ))
                .collect::<Vec<_>>()
                .join(", ")
        )
    }

    fn position(&mut self) -> Result<Pos, DeviceError> {
        Ok([
            self.axes[0].position_um()?,
            self.axes[1].position_um()?,
            self.axes[2].position_um()?,
        ])
    }

    fn target(&mut self) -> Result<Pos, DeviceError> {
        Ok([0, 1, 2].map(|i| self.axes[i].target_um))
    }

    fn move_to(&mut self, target: Pos) -> Result<(), DeviceError> {
        self.do_move(target, None).map(|_| ())
    }

    fn move_to_or_abort(&mut self, target: Pos, abort: &AtomicBool) -> Result<bool, DeviceError> {
        self.do_move(target, Some(abort))
    }

    /// The running mean of the moves measured; before the first, the link model's
    /// [`Kpz101Stage::move_time_prior_s`].
    fn move_time_s(&self) -> f64 {
        self.move_time
            .value()
            .unwrap_or_else(|| self.move_time_prior_s())
    }

    /// The three cubes' links, message by message (summed over the cubes).
    fn link_costs(&mut self) -> crate::instrument::link::LinkCosts {
        crate::instrument::link::summed_costs(self.axes.iter_mut().map(|a| a.take_link_costs()))
    }

    fn enable(&mut self) -> Result<(), DeviceError> {
        for a in &mut self.axes {
            a.enable()?;
        }
        Ok(())
    }

    fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError> {
        Ok([0, 1, 2].map(|i| (0.0, self.axes[i].travel_um)))
    }

    crate::instrument::stage_capabilities!(GaugeZero);

    /// Every cube holds where it is, also when one of them fails (the first error is returned).
    fn stop(&mut self) -> Result<(), DeviceError> {
        all_then_first_error(&mut self.axes, |a| a.hold())
    }
}

/// The cubes' strain gauges, zeroed on request (the Thorlabs family's capability).
impl crate::instrument::GaugeZero for Kpz101Stage {
    fn gauge_zeroed(&self) -> [bool; 3] {
        [0, 1, 2].map(|i| self.axes[i].zeroed)
    }

    /// Zero every cube's gauge in turn (x, y, z). A failure stops there: every cube is told
    /// to hold where it is, and the error names the cube.
    fn zero_gauge(&mut self) -> Result<[bool; 3], DeviceError> {
        for i in 0..3 {
            let t = self.opts.zero_timeout;
            if let Err(e) = self.axes[i].zero(t) {
                let _ = Stage::stop(self);
                return Err(e);
            }
        }
        Ok([0, 1, 2].map(|i| self.axes[i].zeroed))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chan_word_is_le() {
        assert_eq!(chan_word(0x3fff), vec![0x01, 0x00, 0xff, 0x3f]);
    }
}
