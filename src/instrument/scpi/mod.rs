//! Driver for a QPD digitiser speaking bfpscope's small SCPI dialect (documented in full in
//! `docs/hardware.md`):
//!
//! | command                      | reply                                  |
//! |------------------------------|----------------------------------------|
//! | `*IDN?`                      | `maker,model,serial,firmware`          |
//! | `*CLS` / `*RST`              | — (clear error queue / defaults)       |
//! | `SENS:AVER:COUN <n>`         | — (samples averaged per measurement)   |
//! | `SENS:AVER:COUN?`            | `<n>`                                  |
//! | `CONF:RATE?`                 | sample rate in Hz                      |
//! | `MEAS:QPD?`                  | `sx,sy,sz` (volts, mean of n samples)  |
//! | `MEAS:QPD:STAT?`             | `sx,sy,sz,sdx,sdy,sdz` (means and per-sample standard deviations, volts) |
//! | `SYST:ERR?`                  | `0,"No error"` or `-222,"Data out of range"` … (FIFO queue) |
//!
//! Every command is followed by `SYST:ERR?`. Volts become workbench signal units through the
//! configured [`Calibration`]: `signal = gain · (volts − offset_v)` per channel.

pub mod config;
pub use config::FAMILY;
pub mod emulator;

use crate::instrument::link::{open_serial, LineLink, Transport};
use crate::instrument::{DeviceError, Qpd, QpdReading};
use std::time::Duration;

pub use super::tables::Calibration;

/// Driver settings (see `[qpd]` in `bfpscope.toml`).
#[derive(Debug, Clone, PartialEq)]
pub struct ScpiOptions {
    /// Reply timeout for one command, not counting the acquisition itself (the driver adds
    /// `n / sample_rate` for a measurement of `n` samples).
    pub timeout: Duration,
    pub calibration: Calibration,
    /// Use `MEAS:QPD:STAT?` (means and standard deviations); otherwise `MEAS:QPD?` and the
    /// standard deviations are reported as 0.
    pub statistics: bool,
    /// Ask `SYST:ERR?` after every measurement too. A rejected query is never answered (the
    /// dialect's rule), so a well-formed reply already shows the measurement was accepted and
    /// the check is skipped by default (one round trip per point less); a timeout still asks
    /// `SYST:ERR?`. True: the behaviour before the speed work (the bench compares both).
    pub check_error_each_read: bool,
    /// The digitiser's input range ±V (`[qpd] range_v`); `None`: unknown, clipping not
    /// counted. The dialect sends means only: a pixel counts as clipped (all its samples) when
    /// its mean is at the rail; partial clipping within a dwell is not seen.
    pub range_v: Option<f64>,
    /// The sum input below which a pixel is dark, V (`None`: 1 % of `range_v`; 0: no check).
    pub sum_floor_v: Option<f64>,
}

impl Default for ScpiOptions {
    fn default() -> Self {
        Self {
            timeout: Duration::from_millis(1000),
            calibration: Calibration::default(),
            statistics: true,
            check_error_each_read: false,
            range_v: None,
            sum_floor_v: None,
        }
    }
}

pub use crate::instrument::scpi_session::parse_scpi_error;
use crate::instrument::scpi_session::ScpiSession;

/// Parse `k` comma-separated finite numbers.
pub fn parse_numbers(reply: &str, k: usize) -> Option<Vec<f64>> {
    let v: Vec<f64> = reply
        .split(',')
        .map(|s| s.trim().parse::<f64>().ok().filter(|x| x.is_finite()))
        .collect::<Option<_>>()?;
    (v.len() == k).then_some(v)
}

/// A QPD digitiser on a serial line.
pub struct ScpiQpd {
    link: LineLink,
    opts: ScpiOptions,
    idn: String,
    rate: f64,
    /// Averaging count last set on the device (so it is only sent when it changes).
    count: Option<usize>,
    /// Wall time per read beyond the samples' own n / rate, s: a running mean for the ETA.
    overhead: crate::instrument::gcs::MeanTime,
    /// The serial line's bytes per second (baud / 10), for the link model before any read.
    wire_bytes_per_s: Option<f64>,
}

impl ScpiQpd {
    /// Open a serial port and connect.
    pub fn open(port: &str, baud: u32, opts: ScpiOptions) -> Result<Self, DeviceError> {
        let device = format!("SCPI QPD on {port}");
        let io = open_serial(&device, port, baud, opts.timeout)?;
        let mut q = Self::connect(io, port, opts)?;
        q.wire_bytes_per_s = (baud > 0).then(|| f64::from(baud) / 10.0);
        Ok(q)
    }

    /// Connect over any transport: `*IDN?`, `*CLS`, `CONF:RATE?`.
    pub fn connect(
        io: Box<dyn Transport>,
        port: &str,
        opts: ScpiOptions,
    ) -> Result<Self, DeviceError> {
        let link = LineLink::new(io, format!("SCPI QPD on {port}"), opts.timeout);
        let mut q = Self {
            link,
            opts,
            idn: String::new(),
            rate: 0.0,
            count: None,
            overhead: Default::default(),
            wire_bytes_per_s: None,
        };
        q.idn = q.query("*IDN?")?.trim().to_string();
        if let Some(model) = q
            .idn
            .split(',')
            .nth(1)
            .map(str::trim)
            .filter(|m| !m.is_empty())
        {
            q.link.set_device(format!("QPD {model} on {port}"));
        }
        q.command("*CLS")?;
        let r = q.query("CONF:RATE?")?;
        q.rate = match r.trim().parse::<f64>() {
            Ok(v) if v.is_finite() && v > 0.0 => v,
            _ => return Err(q.link.garbled("CONF:RATE?", r)),
        };
        Ok(q)
    }

    pub fn idn(&self) -> &str {
        &self.idn
    }

    pub fn options(&self) -> &ScpiOptions {
        &self.opts
    }

    /// `SYST:ERR?`; a nonzero code is a `Controller` error naming `after` ([`ScpiSession`]).
    pub fn check_error(&mut self, after: &str) -> Result<(), DeviceError> {
        self.link.check_error(after, self.opts.timeout)
    }

    /// Send a command without reply, then check the error queue ([`ScpiSession`]).
    pub fn command(&mut self, command: &str) -> Result<(), DeviceError> {
        self.link.scpi_command(command, self.opts.timeout)
    }

    /// Send a query and return its reply line ([`ScpiSession`]: a silent query asks the error
    /// queue once).
    pub fn query(&mut self, command: &str) -> Result<String, DeviceError> {
        self.query_timeout(command, self.opts.timeout)
    }

    fn query_timeout(&mut self, command: &str, timeout: Duration) -> Result<String, DeviceError> {
        self.link.scpi_query(command, timeout)
    }

    /// Set the number of samples averaged per measurement (only sent when it changes).
    pub fn set_count(&mut self, n: usize) -> Result<(), DeviceError> {
        if self.count == Some(n) {
            return Ok(());
        }
        self.count = None;
        self.command(&format!("SENS:AVER:COUN {n}"))?;
        self.count = Some(n);
        Ok(())
    }

    /// One measurement in volts: means and per-sample standard deviations.
    pub fn measure_volts(&mut self, n: usize) -> Result<([f64; 3], [f64; 3]), DeviceError> {
        self.measure(n, self.opts.statistics)
    }

    /// One measurement in volts: `MEAS:QPD:STAT?` (means and standard deviations) when
    /// `statistics`, else `MEAS:QPD?` (means; standard deviations 0).
    fn measure(&mut self, n: usize, statistics: bool) -> Result<([f64; 3], [f64; 3]), DeviceError> {
        self.set_count(n)?;
        let acquisition = Duration::from_secs_f64((n as f64 / self.rate).min(3600.0));
        let timeout = self.opts.timeout + acquisition;
        let (cmd, k) = if statistics {
            ("MEAS:QPD:STAT?", 6)
        } else {
            ("MEAS:QPD?", 3)
        };
        let line = self.query_timeout(cmd, timeout)?;
        let v = parse_numbers(&line, k).ok_or_else(|| self.link.garbled(cmd, line.clone()))?;
        if self.opts.check_error_each_read {
            self.check_error(cmd)?;
        }
        let std = if k == 6 { [v[3], v[4], v[5]] } else { [0.0; 3] };
        if std.iter().any(|s| *s < 0.0) {
            return Err(self.link.garbled(cmd, line));
        }
        Ok(([v[0], v[1], v[2]], std))
    }
}

impl ScpiQpd {
    /// A reading of `n` samples with means `v` (V): every sample counted clipped on a channel
    /// whose mean is at the rail (the dialect sends no samples).
    fn reading(&self, v: [f64; 3], s: [f64; 3], n: usize) -> QpdReading {
        let clipped = match self.opts.range_v {
            Some(r) => v.map(|x| {
                if crate::instrument::range::at_rail(x, r) {
                    n
                } else {
                    0
                }
            }),
            None => [0; 3],
        };
        QpdReading {
            clipped,
            ..self.opts.calibration.apply(v, s, n)
        }
    }
}

impl Qpd for ScpiQpd {
    fn name(&self) -> String {
        self.link.device().to_string()
    }

    fn sample_rate(&self) -> f64 {
        self.rate
    }

    fn read(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        let t0 = std::time::Instant::now();
        let (v, s) = self.measure_volts(n)?;
        self.overhead
            .add(t0.elapsed().as_secs_f64() - n as f64 / self.rate);
        Ok(self.reading(v, s, n))
    }

    /// `MEAS:QPD?`: three numbers (about 50 bytes) instead of `MEAS:QPD:STAT?`'s six (about
    /// 100 bytes, 9 ms at 115200 baud), whatever `statistics` says: scans store the means only.
    fn read_means(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        let t0 = std::time::Instant::now();
        let (v, s) = self.measure(n, false)?;
        self.overhead
            .add(t0.elapsed().as_secs_f64() - n as f64 / self.rate);
        Ok(self.reading(v, s, n))
    }

    /// The running mean of the reads measured; before the first (the first scan after
    /// connecting), the link model: `MEAS:QPD?` (10 bytes) and its reply, three numbers at full
    /// double precision (~15 characters) with their separators and the line end (48 bytes), at
    /// the configured baud rate (10 bits per byte), plus the link's latency measured on every
    /// reply so far (the connect's `*IDN?` and `CONF:RATE?`), and the same again for the
    /// `SYST:ERR?` after each read when `check_error_each_read` (reply `0,"No error"`, ~13
    /// bytes).
    fn overhead_s(&self) -> f64 {
        if let Some(m) = self.overhead.value() {
            return m;
        }
        let Some(lat) = self.link.latency_s(self.wire_bytes_per_s) else {
            return 0.0;
        };
        let reply = |bytes: f64| lat + self.wire_bytes_per_s.map_or(0.0, |r| bytes / r);
        reply(10.0 + 48.0)
            + if self.opts.check_error_each_read {
                reply(10.0 + 13.0)
            } else {
                0.0
            }
    }

    fn link_costs(&mut self) -> crate::instrument::link::LinkCosts {
        self.link.take_costs()
    }

    /// ±`range_v` when configured; the sum floor (default 1 % of the range).
    fn input_range(&self) -> Option<crate::instrument::range::InputRange> {
        let r = self.opts.range_v?;
        let c = &self.opts.calibration;
        Some(crate::instrument::range::InputRange::new(r, "V").with_sum(
            Some(self.opts.sum_floor_v.unwrap_or(0.01 * r)).filter(|f| *f > 0.0),
            c.gain[2],
            c.offset_v[2],
        ))
    }
}

/// The SCPI QPD digitiser (the QPD), read beside a PI stage. (listed in `instrument::registry`).
/// SCPI QPD digitiser: a `[qpd]` backend.
pub const SCPI: crate::instrument::family::Backend = crate::instrument::family::Backend("scpi");

#[cfg(test)]
mod tests {
    use super::*;
    use crate::instrument::link::mock::Scripted;
    use proptest::prelude::*;

    fn qpd(replies: Vec<&[u8]>) -> ScpiQpd {
        let mut all: Vec<Vec<u8>> = vec![
            b"bfpscope,QPD-1,0001,1.0\n".to_vec(),
            b"".to_vec(),
            b"0,\"No error\"\n".to_vec(),
            b"1.0e5\n".to_vec(),
        ];
        all.extend(replies.into_iter().map(|r| r.to_vec()));
        let opts = ScpiOptions {
            timeout: Duration::from_millis(10),
            calibration: Calibration {
                gain: [2.0, 2.0, -1.0],
                offset_v: [0.5, 0.0, 0.0],
            },
            statistics: true,
            check_error_each_read: true,
            ..ScpiOptions::default()
        };
        ScpiQpd::connect(Box::new(Scripted::new(all)), "mock", opts).unwrap()
    }

    const OK: &[u8] = b"0,\"No error\"\n";

    #[test]
    fn reads_and_calibrates() {
        let mut q = qpd(vec![b"", OK, b"1.5,0.25,-2,0.1,0.2,0.3\n", OK]);
        assert_eq!(q.name(), "QPD QPD-1 on mock");
        assert_eq!(q.sample_rate(), 1.0e5);
        let r = q.read(100).unwrap();
        assert_eq!((r.sx, r.sy, r.sz), (2.0, 0.5, 2.0));
        assert_eq!((r.sx_std, r.sy_std, r.sz_std), (0.2, 0.4, 0.3));
        assert_eq!(r.n, 100);
    }

    #[test]
    fn device_error_queue() {
        let mut q = qpd(vec![b"", b"-222,\"Data out of range\"\n"]);
        match q.read(0) {
            Err(DeviceError::Controller {
                code,
                message,
                command,
                ..
            }) => {
                assert_eq!(
                    (code, message.as_str(), command.as_str()),
                    (-222, "Data out of range", "SENS:AVER:COUN 0")
                );
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn parsers() {
        assert_eq!(
            parse_scpi_error("-113,\"Undefined header\""),
            Some((-113, "Undefined header".into()))
        );
        assert_eq!(parse_scpi_error("0,No error"), None);
        assert_eq!(parse_numbers("1,2,3", 3), Some(vec![1.0, 2.0, 3.0]));
        assert_eq!(parse_numbers("1,2", 3), None);
        assert_eq!(parse_numbers("1,nan,3", 3), None);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]
        #[test]
        fn garbage_never_panics(reply in proptest::collection::vec(any::<u8>(), 0..200)) {
            let mut q = qpd(vec![b"", OK, &reply, OK, OK]);
            match q.read(10) {
                Ok(r) => prop_assert!(r.sx.is_finite() && r.sz_std >= 0.0),
                Err(DeviceError::Garbled { .. }) | Err(DeviceError::Timeout { .. }) => {}
                Err(e) => prop_assert!(false, "unexpected {e:?}"),
            }
        }
    }
}
