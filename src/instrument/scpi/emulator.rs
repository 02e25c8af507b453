//! A QPD digitiser emulator speaking bfpscope's SCPI dialect (see `docs/hardware.md`).
//!
//! A measurement of n samples reads the shared stage position, asks the [`SignalSource`] for
//! (Sx, Sy, Sz), converts to volts (`volts = volts_per_unit · signal + offset_v`), adds white
//! noise per sample (`noise_v`, volts rms) and returns the means (and, for
//! `MEAS:QPD:STAT?`, the per-sample standard deviations). With `realtime` the reply takes
//! n / rate seconds, as the hardware would.
//!
//! Headers take SCPI short or long forms, any case (`SENS:AVER:COUN`,
//! `sense:average:count`). Errors go to a FIFO queue of 16 read with `SYST:ERR?`.

use crate::instrument::emulation::{
    lock, pty_line, spawn, Device, Emulator, Faults, LinkModel, SharedPosition, SignalSource,
};
use rand::{Rng, SeedableRng};
use std::collections::VecDeque;
use std::sync::{Arc, Mutex};

/// QPD emulator settings.
#[derive(Debug, Clone, PartialEq)]
pub struct QpdEmulatorConfig {
    /// `*IDN?` reply.
    pub idn: String,
    /// Sample rate, Hz (`CONF:RATE?`).
    pub sample_rate_hz: f64,
    /// Analog gain of the emulated detector: volts per signal unit, per channel.
    pub volts_per_unit: [f64; 3],
    /// Output offset, volts, per channel.
    pub offset_v: [f64; 3],
    /// White noise per sample, volts rms, per channel.
    pub noise_v: [f64; 3],
    /// Take n / rate seconds to answer a measurement of n samples.
    pub realtime: bool,
    /// Noise seed (reproducible runs).
    pub seed: u64,
    /// Largest averaging count accepted (`SENS:AVER:COUN`).
    pub max_count: usize,
    /// Initial fault switches.
    pub faults: Faults,
    /// The serial link modelled (baud rate, reply latency); default the pty's full speed.
    pub link: LinkModel,
}

impl Default for QpdEmulatorConfig {
    fn default() -> Self {
        Self {
            idn: "bfpscope,QPD-EMU,0001,1.0".into(),
            sample_rate_hz: 100_000.0,
            volts_per_unit: [1.0; 3],
            offset_v: [0.0; 3],
            noise_v: [1e-4; 3],
            realtime: true,
            seed: 1,
            max_count: 1_000_000,
            faults: Faults::default(),
            link: LinkModel::FULL_SPEED,
        }
    }
}

/// Text of the SCPI error codes the dialect uses.
pub fn scpi_error_text(code: i64) -> &'static str {
    match code {
        0 => "No error",
        -102 => "Syntax error",
        -104 => "Data type error",
        -108 => "Parameter not allowed",
        -109 => "Missing parameter",
        -113 => "Undefined header",
        -222 => "Data out of range",
        -350 => "Queue overflow",
        _ => "Device-specific error",
    }
}

const QUEUE: usize = 16;

struct ScpiDevice {
    cfg: QpdEmulatorConfig,
    count: usize,
    errors: VecDeque<i64>,
    position: SharedPosition,
    source: Box<dyn SignalSource>,
    rng: rand_chacha::ChaCha8Rng,
}

/// Does `header` (e.g. `SENS:AVER:COUN?`) match `pattern` (`SENSe:AVERage:COUNt?`)? Each node
/// may be given in its short form (the capitals) or its long form, in any case.
pub fn scpi_match(header: &str, pattern: &str) -> bool {
    let h = header.strip_prefix(':').unwrap_or(header);
    let (h, hq) = match h.strip_suffix('?') {
        Some(x) => (x, true),
        None => (h, false),
    };
    let (p, pq) = match pattern.strip_suffix('?') {
        Some(x) => (x, true),
        None => (pattern, false),
    };
    if hq != pq {
        return false;
    }
    let hn: Vec<&str> = h.split(':').collect();
    let pn: Vec<&str> = p.split(':').collect();
    hn.len() == pn.len()
        && hn.iter().zip(&pn).all(|(h, p)| {
            let short: String = p.chars().filter(|c| !c.is_ascii_lowercase()).collect();
            h.eq_ignore_ascii_case(&short) || h.eq_ignore_ascii_case(p)
        })
}

impl ScpiDevice {
    fn push_error(&mut self, code: i64) {
        if self.errors.len() >= QUEUE {
            // SCPI: the newest entry becomes "Queue overflow".
            if let Some(last) = self.errors.back_mut() {
                *last = -350;
            }
        } else {
            self.errors.push_back(code);
        }
    }

    /// Means and per-sample standard deviations of n samples, volts.
    ///
    /// In real time (`cfg.realtime`) the reply comes the acquisition time n / rate after the
    /// command, as a digitiser's: the emulator's own work (the scene at the stage position, the
    /// samples' noise) happens within that time, not before it.
    fn measure(&mut self) -> [f64; 6] {
        let started = std::time::Instant::now();
        let p = *lock(&self.position);
        let s = (self.source)(p);
        let n = self.count.max(1);
        let mut out = [0.0; 6];
        for c in 0..3 {
            let v = self.cfg.volts_per_unit[c] * s[c] + self.cfg.offset_v[c];
            let sigma = self.cfg.noise_v[c].abs();
            if sigma == 0.0 || !sigma.is_finite() {
                out[c] = v;
                continue;
            }
            let normal = rand_distr::Normal::new(0.0, sigma).expect("finite sigma");
            let (mut sum, mut sum2) = (0.0, 0.0);
            for _ in 0..n {
                let e: f64 = self.rng.sample(normal);
                sum += e;
                sum2 += e * e;
            }
            let mean = sum / n as f64;
            out[c] = v + mean;
            out[c + 3] = if n > 1 {
                ((sum2 - n as f64 * mean * mean) / (n as f64 - 1.0))
                    .max(0.0)
                    .sqrt()
            } else {
                0.0
            };
        }
        if self.cfg.realtime {
            let t = (n as f64 / self.cfg.sample_rate_hz).min(10.0);
            if t > 0.0 && t.is_finite() {
                let left = std::time::Duration::from_secs_f64(t).saturating_sub(started.elapsed());
                std::thread::sleep(left);
            }
        }
        out
    }
}

impl Device for ScpiDevice {
    fn is_error_query(&self, line: &str) -> bool {
        let h = line.split_whitespace().next().unwrap_or("");
        scpi_match(h, "SYSTem:ERRor?") || scpi_match(h, "SYSTem:ERRor:NEXT?")
    }

    fn inject_error(&mut self, code: i64) {
        self.push_error(code);
    }

    fn handle(&mut self, line: &str) -> Option<String> {
        let line = line.trim();
        let (header, arg) = match line.split_once(char::is_whitespace) {
            Some((h, a)) => (h, Some(a.trim())),
            None => (line, None),
        };
        let is = |p: &str| scpi_match(header, p);
        let no_arg = |d: &mut Self| {
            if arg.is_some() {
                d.push_error(-108);
                false
            } else {
                true
            }
        };
        if is("*IDN?") {
            return no_arg(self).then(|| self.cfg.idn.clone());
        }
        if is("*CLS") {
            if no_arg(self) {
                self.errors.clear();
            }
            return None;
        }
        if is("*RST") {
            if no_arg(self) {
                self.count = 1;
                self.errors.clear();
            }
            return None;
        }
        if is("SYSTem:ERRor?") || is("SYSTem:ERRor:NEXT?") {
            let code = self.errors.pop_front().unwrap_or(0);
            return Some(format!("{code},\"{}\"", scpi_error_text(code)));
        }
        if is("SENSe:AVERage:COUNt") {
            match arg.map(str::parse::<i64>) {
                None => self.push_error(-109),
                Some(Err(_)) => self.push_error(-104),
                Some(Ok(n)) if n < 1 || n as u64 > self.cfg.max_count as u64 => {
                    self.push_error(-222)
                }
                Some(Ok(n)) => self.count = n as usize,
            }
            return None;
        }
        if is("SENSe:AVERage:COUNt?") {
            return no_arg(self).then(|| self.count.to_string());
        }
        if is("CONFigure:RATE?") {
            return no_arg(self).then(|| format!("{:.6e}", self.cfg.sample_rate_hz));
        }
        if is("MEASure:QPD?") || is("MEASure:QPD:STATistics?") {
            if !no_arg(self) {
                return None;
            }
            let m = self.measure();
            let k = if is("MEASure:QPD?") { 3 } else { 6 };
            let parts: Vec<String> = m[..k].iter().map(|v| format!("{v:.9e}")).collect();
            return Some(parts.join(","));
        }
        self.push_error(-113);
        None
    }
}

/// Start a QPD emulator on a new pseudo-terminal, answering with `source` evaluated at the
/// shared stage `position`.
pub fn start_qpd_emulator(
    cfg: QpdEmulatorConfig,
    position: SharedPosition,
    source: impl SignalSource,
) -> std::io::Result<Emulator> {
    let faults = Arc::new(Mutex::new(cfg.faults.clone()));
    let link = cfg.link;
    let rng = rand_chacha::ChaCha8Rng::seed_from_u64(cfg.seed);
    let dev = ScpiDevice {
        cfg,
        count: 1,
        errors: VecDeque::new(),
        position: position.clone(),
        source: Box::new(source),
        rng,
    };
    spawn("qpd", dev, faults, position, pty_line()?, link)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn short_and_long_forms() {
        assert!(scpi_match("SENS:AVER:COUN", "SENSe:AVERage:COUNt"));
        assert!(scpi_match(":sense:average:count", "SENSe:AVERage:COUNt"));
        assert!(scpi_match("MEAS:QPD:STAT?", "MEASure:QPD:STATistics?"));
        assert!(!scpi_match("MEAS:QPD:STAT", "MEASure:QPD:STATistics?"));
        assert!(!scpi_match("SENS:AVE:COUN", "SENSe:AVERage:COUNt"));
        assert!(!scpi_match("MEAS:QPD?", "MEASure:QPD:STATistics?"));
        assert!(scpi_match("*idn?", "*IDN?"));
    }

    fn dev(noise: f64) -> ScpiDevice {
        let cfg = QpdEmulatorConfig {
            noise_v: [noise; 3],
            realtime: false,
            ..Default::default()
        };
        ScpiDevice {
            cfg,
            count: 1,
            errors: VecDeque::new(),
            position: crate::instrument::emulation::shared_position([0.1, 0.0, 0.0]),
            source: Box::new(crate::instrument::emulation::standin_bead),
            rng: rand_chacha::ChaCha8Rng::seed_from_u64(3),
        }
    }

    #[test]
    fn error_queue_is_fifo_and_overflows() {
        let mut d = dev(0.0);
        assert_eq!(d.handle("SENS:AVER:COUN 0"), None);
        assert_eq!(d.handle("BOGUS"), None);
        assert_eq!(d.handle("SYST:ERR?").unwrap(), "-222,\"Data out of range\"");
        assert_eq!(d.handle("SYST:ERR?").unwrap(), "-113,\"Undefined header\"");
        assert_eq!(d.handle("SYST:ERR?").unwrap(), "0,\"No error\"");
        for _ in 0..20 {
            d.handle("BOGUS");
        }
        let codes: Vec<String> = (0..QUEUE + 1)
            .map(|_| d.handle("SYST:ERR?").unwrap())
            .collect();
        assert!(codes[QUEUE - 1].starts_with("-350"), "{codes:?}");
        assert!(codes[QUEUE].starts_with("0,"));
    }

    #[test]
    fn noise_shrinks_with_averaging() {
        let mut d = dev(0.01);
        let exact = standin(0.1);
        d.handle("SENS:AVER:COUN 10000");
        let r = d.handle("MEAS:QPD:STAT?").unwrap();
        let v: Vec<f64> = r.split(',').map(|s| s.parse().unwrap()).collect();
        assert!((v[0] - exact).abs() < 5.0 * 0.01 / 100.0, "{v:?}");
        assert!((v[3] - 0.01).abs() < 0.0005, "per-sample std {v:?}");
    }

    fn standin(x: f64) -> f64 {
        x * (-x * x / 0.16).exp()
    }
}
