//! Thorlabs KPA101 (K-Cube) / TPA101 (T-Cube) position aligner as the QPD: it digitises a
//! quadrant detector's X difference, Y difference and Sum. bfpscope only reads it: at connect
//! the cube is put in **monitor mode** (`MGMSG_QUAD_SET_PARAMS`, sub-message 0x07, mode 1), in
//! which its X/Y outputs drive nothing, and that mode is read back.
//!
//! A reading is `MGMSG_QUAD_REQ_PARAMS` with sub-message 0x03 ("readings"), answered by
//! `MGMSG_QUAD_GET_PARAMS` with 12 data bytes: sub-message id (u16), XDiff (i16), YDiff (i16),
//! Sum (u16), XPos (i16), YPos (i16). Per Thorlabs' document the differences span ±10 V over
//! ±32767 counts and the Sum 0–10 V over 0–65535 counts. `read(n)` asks n times and averages:
//!
//! ```text
//! Xdiff_V = x_sign · XDiff · 10/32767      Ydiff_V = YDiff · 10/32767      Sum_V = Sum · sum_scale
//! Sx = gain_x · (Xdiff_V − offset_x) / Sum_V
//! Sy = gain_y · (Ydiff_V − offset_y) / Sum_V
//! Sz = gain_z · (Sum_V − offset_z)
//! ```
//!
//! Sx and Sy are the normalised differences (dimensionless: independent of laser power, as the
//! paper's Sx = (I_left − I_right)/I_total); Sz is the Sum in volts unless the calibration says
//! otherwise (gain_z = 1/Sum₀, offset_z = Sum₀ gives the relative change of the total power).
//! The points on which public sources disagree (Sum scaling, sign of X, Sum signed or not) are
//! options ([`KpaOptions`]); see docs/hardware.md.

use super::{hex, id, open_apt_serial, AptLink, HwInfo, Message};
use crate::instrument::link::Transport;
use crate::instrument::scpi::Calibration;
use crate::instrument::{DeviceError, Qpd, QpdReading};
use std::time::{Duration, Instant};

/// Sub-message of `MGMSG_QUAD_*_PARAMS`: the live readings.
pub const SUB_READINGS: u8 = 0x03;
/// Sub-message of `MGMSG_QUAD_*_PARAMS`: the operating mode.
pub const SUB_OPER_MODE: u8 = 0x07;
/// Operating modes (sub-message 0x07).
pub const MODE_MONITOR: u16 = 1;
pub const MODE_OPEN_LOOP: u16 = 2;
pub const MODE_CLOSED_LOOP: u16 = 3;
pub const MODE_AUTO: u16 = 4;
/// Volts per count of XDiff and YDiff (±10 V over ±32767 counts).
pub const DIFF_V_PER_COUNT: f64 = 10.0 / 32767.0;
/// Volts per count of Sum per Thorlabs' document (0–10 V over 0–65535 counts): the default.
pub const SUM_V_PER_COUNT_DOC: f64 = 10.0 / 65535.0;

/// Driver settings (`[qpd]` with `backend = "kpa101"`).
#[derive(Debug, Clone, PartialEq)]
pub struct KpaOptions {
    pub timeout: Duration,
    pub calibration: Calibration,
    /// Volts per count of the Sum reading (document: 10/65535; pylablib: 20/32767).
    pub sum_scale: f64,
    /// +1 or −1: sign applied to XDiff (pylablib inverts it, the document does not).
    pub x_sign: f64,
    /// Read Sum as a signed 16-bit number (the document: unsigned).
    pub signed: bool,
    /// RTS/CTS flow control on the port (Thorlabs' FTDI bridge: yes).
    pub rtscts: bool,
    /// The Sum (V) below which a pixel is dark (`[qpd] sum_floor`; `None`: 0.1 V, 1 % of the
    /// Sum's 10 V; 0: not checked).
    pub sum_floor_v: Option<f64>,
}

impl Default for KpaOptions {
    fn default() -> Self {
        Self {
            timeout: Duration::from_millis(1000),
            calibration: Calibration::default(),
            sum_scale: SUM_V_PER_COUNT_DOC,
            x_sign: 1.0,
            signed: false,
            rtscts: true,
            sum_floor_v: None,
        }
    }
}

/// One decoded reading in counts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RawReading {
    pub xdiff: i16,
    pub ydiff: i16,
    /// The Sum word as sent (interpret with [`KpaOptions::signed`]).
    pub sum: u16,
    pub xpos: i16,
    pub ypos: i16,
}

impl RawReading {
    /// Decode the `MGMSG_QUAD_GET_PARAMS` readings packet (12 bytes, sub-message 0x03).
    pub fn decode(d: &[u8]) -> Option<Self> {
        if d.len() != 12 || u16::from_le_bytes([d[0], d[1]]) != SUB_READINGS as u16 {
            return None;
        }
        let w = |i: usize| u16::from_le_bytes([d[i], d[i + 1]]);
        Some(Self {
            xdiff: w(2) as i16,
            ydiff: w(4) as i16,
            sum: w(6),
            xpos: w(8) as i16,
            ypos: w(10) as i16,
        })
    }

    /// Encode as the readings packet (emulators).
    pub fn encode(&self) -> Vec<u8> {
        let mut d = Vec::with_capacity(12);
        for w in [
            SUB_READINGS as u16,
            self.xdiff as u16,
            self.ydiff as u16,
            self.sum,
            self.xpos as u16,
            self.ypos as u16,
        ] {
            d.extend_from_slice(&w.to_le_bytes());
        }
        d
    }
}

/// A KPA101/TPA101 on a serial port.
pub struct Kpa101 {
    link: AptLink,
    opts: KpaOptions,
    info: HwInfo,
    rate: f64,
    port: String,
}

impl Kpa101 {
    /// Open the port (115200 8N1, RTS/CTS) and connect.
    pub fn open(port: &str, opts: KpaOptions) -> Result<Self, DeviceError> {
        let device = format!("Thorlabs KPA101 on {port}");
        let io = if opts.rtscts {
            open_apt_serial(&device, port, opts.timeout)?
        } else {
            crate::instrument::link::open_serial(&device, port, 115_200, opts.timeout)?
        };
        Self::connect(io, port, opts)
    }

    /// Connect over any transport: `MGMSG_HW_NO_FLASH_PROGRAMMING`, `MGMSG_HW_STOP_UPDATEMSGS`,
    /// `MGMSG_HW_REQ_INFO` (the model must be a position aligner), monitor mode set and read
    /// back, then five readings timed for the sample rate.
    pub fn connect(
        io: Box<dyn Transport>,
        port: &str,
        opts: KpaOptions,
    ) -> Result<Self, DeviceError> {
        let mut link = AptLink::new(io, format!("Thorlabs KPA101 on {port}"), opts.timeout);
        let info = link.identify()?;
        let model = info.model.to_ascii_uppercase();
        if !(model.starts_with("KPA") || model.starts_with("TPA") || model.starts_with("TQD")) {
            return Err(DeviceError::Other {
                device: link.device().to_string(),
                detail: format!(
                    "`{}` answered model {:?} (serial {}): not a position aligner (KPA101, TPA101, TQD001); \
                     check qpd.port",
                    Message::short(id::HW_REQ_INFO, 0, 0).describe(),
                    info.model,
                    info.serial
                ),
            });
        }
        link.set_device(format!(
            "Thorlabs {} #{} on {port}",
            info.model, info.serial
        ));
        let mut q = Self {
            link,
            opts,
            info,
            rate: 0.0,
            port: port.to_string(),
        };
        q.set_monitor_mode()?;
        let t0 = Instant::now();
        for _ in 0..5 {
            q.read_raw()?;
        }
        let dt = t0.elapsed().as_secs_f64() / 5.0;
        q.rate = if dt > 0.0 { 1.0 / dt } else { 1000.0 };
        Ok(q)
    }

    /// Monitor mode (the aligner's outputs drive nothing), read back.
    fn set_monitor_mode(&mut self) -> Result<(), DeviceError> {
        let mut d = (SUB_OPER_MODE as u16).to_le_bytes().to_vec();
        d.extend_from_slice(&MODE_MONITOR.to_le_bytes());
        self.link.send(&Message::long(id::QUAD_SET_PARAMS, d))?;
        let req = Message::short(id::QUAD_REQ_PARAMS, SUB_OPER_MODE, 0);
        let r = self.link.request(&req, id::QUAD_GET_PARAMS)?;
        let d = r.bytes();
        if d.len() != 4 || d[0] != SUB_OPER_MODE || d[1] != 0 {
            return Err(self.garbled(&req, &r, "sub-message 0x07 with a 2-byte mode"));
        }
        let mode = u16::from_le_bytes([d[2], d[3]]);
        if mode != MODE_MONITOR {
            return Err(DeviceError::Other {
                device: self.link.device().to_string(),
                detail: format!(
                    "set to monitor mode (1), but `{}` answered mode {mode}: the cube may still drive its \
                     outputs; not used",
                    req.describe()
                ),
            });
        }
        Ok(())
    }

    fn garbled(&self, req: &Message, r: &Message, expected: &str) -> DeviceError {
        DeviceError::Garbled {
            device: self.link.device().to_string(),
            command: req.describe(),
            reply: format!("{} (expected {expected})", r.describe()),
        }
    }

    /// One reading in counts.
    pub fn read_raw(&mut self) -> Result<RawReading, DeviceError> {
        let req = Message::short(id::QUAD_REQ_PARAMS, SUB_READINGS, 0);
        let r = self.link.request(&req, id::QUAD_GET_PARAMS)?;
        RawReading::decode(r.bytes())
            .ok_or_else(|| self.garbled(&req, &r, "sub-message 0x03 with 10 bytes of readings"))
    }

    /// (Xdiff, Ydiff, Sum) in volts, with the configured conventions.
    pub fn volts(&self, r: &RawReading) -> [f64; 3] {
        let sum = if self.opts.signed {
            r.sum as i16 as f64
        } else {
            r.sum as f64
        };
        [
            self.opts.x_sign * r.xdiff as f64 * DIFF_V_PER_COUNT,
            r.ydiff as f64 * DIFF_V_PER_COUNT,
            sum * self.opts.sum_scale,
        ]
    }

    /// Which of XDiff, YDiff, Sum are at the ADC's end (±32767 counts for the differences;
    /// the Sum's top count, 65535, or 32767 when read signed).
    pub fn clipped(&self, r: &RawReading) -> [bool; 3] {
        let top = if self.opts.signed {
            r.sum as i16 == i16::MAX
        } else {
            r.sum == u16::MAX
        };
        [
            r.xdiff.unsigned_abs() >= 32767,
            r.ydiff.unsigned_abs() >= 32767,
            top,
        ]
    }

    pub fn info(&self) -> &HwInfo {
        &self.info
    }

    pub fn port(&self) -> &str {
        &self.port
    }

    pub fn options(&self) -> &KpaOptions {
        &self.opts
    }
}

impl Qpd for Kpa101 {
    fn name(&self) -> String {
        self.link.device().to_string()
    }

    /// Readings per second as timed at connect (each reading is one request and reply; the
    /// aligner is not sampled on a clock).
    fn sample_rate(&self) -> f64 {
        self.rate
    }

    fn read(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        let n = n.max(1);
        let c = self.opts.calibration;
        let mut s = [
            Vec::with_capacity(n),
            Vec::with_capacity(n),
            Vec::with_capacity(n),
        ];
        let mut clipped = [0usize; 3];
        for _ in 0..n {
            let raw = self.read_raw()?;
            for (c, hit) in clipped.iter_mut().zip(self.clipped(&raw)) {
                *c += hit as usize;
            }
            let [xd, yd, sum] = self.volts(&raw);
            if sum.is_nan() || sum <= 0.0 {
                return Err(DeviceError::Other {
                    device: self.name(),
                    detail: format!(
                        "`{}` answered Sum = {sum} V (raw [{}]): no light on the detector, Sx = Xdiff/Sum \
                         is undefined",
                        Message::short(id::QUAD_REQ_PARAMS, SUB_READINGS, 0).describe(),
                        hex(&raw.encode())
                    ),
                });
            }
            s[0].push(c.gain[0] * (xd - c.offset_v[0]) / sum);
            s[1].push(c.gain[1] * (yd - c.offset_v[1]) / sum);
            s[2].push(c.gain[2] * (sum - c.offset_v[2]));
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let std = |v: &[f64]| {
            if v.len() < 2 {
                return 0.0;
            }
            let m = mean(v);
            (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
        };
        Ok(QpdReading {
            sx: mean(&s[0]),
            sy: mean(&s[1]),
            sz: mean(&s[2]),
            sx_std: std(&s[0]),
            sy_std: std(&s[1]),
            sz_std: std(&s[2]),
            n,
            clipped,
        })
    }

    /// ±10 V (the differences' ADC; the Sum spans 0–10 V), the Sum's floor (default 0.1 V).
    fn input_range(&self) -> Option<crate::instrument::range::InputRange> {
        let c = &self.opts.calibration;
        Some(
            crate::instrument::range::InputRange::new(10.0, "V").with_sum(
                Some(self.opts.sum_floor_v.unwrap_or(0.1)).filter(|f| *f > 0.0),
                c.gain[2],
                c.offset_v[2],
            ),
        )
    }

    fn link_costs(&mut self) -> crate::instrument::link::LinkCosts {
        self.link.take_costs()
    }

    fn metadata(&self) -> Option<serde_json::Value> {
        Some(serde_json::json!({
            "device": self.info,
            "sum_scale_v_per_count": self.opts.sum_scale,
            "x_sign": self.opts.x_sign,
            "sum_signed": self.opts.signed,
            "mode": "monitor",
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn readings_packet_round_trip_and_signs() {
        let r = RawReading {
            xdiff: -16384,
            ydiff: 1000,
            sum: 40000,
            xpos: 0,
            ypos: -1,
        };
        let d = r.encode();
        assert_eq!(
            d,
            vec![0x03, 0x00, 0x00, 0xc0, 0xe8, 0x03, 0x40, 0x9c, 0x00, 0x00, 0xff, 0xff]
        );
        assert_eq!(RawReading::decode(&d), Some(r));
        // Sum 40000 counts: above i16::MAX, negative if read signed
        assert_eq!(r.sum as i16, -25536);
        let mut bad = d.clone();
        bad[0] = 0x07;
        assert_eq!(RawReading::decode(&bad), None);
        assert_eq!(RawReading::decode(&d[..11]), None);
    }
}
