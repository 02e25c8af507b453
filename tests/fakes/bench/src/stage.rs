//! The Nano-Drive and its Nano-PDQ375 stage: three closed-loop axes (Madlib numbering x = 1,
//! y = 2, z = 3) with a calibrated range each (75 × 75 × 50 µm by default), whose sensor
//! follows the target with a first-order lag, and an external analog input per axis
//! (0–10 V over the calibrated range, driven by the PCI-6120's AO channels).
//!
//! How the external input and the USB command combine (setting `ext_mode`): by default, as
//! MCL describes the Nano-Drive's external analog input, its position is *added* to the
//! position commanded over USB (`sum`: target = USB + external, clamped to the range); a
//! `replace` controller follows whichever of the two changed last.
//!
//! Each axis keeps the history of its target changes, each with the position at that instant,
//! so that the position at any past instant is exact: `p(t) = T + (p_k − T)·exp(−(t − t_k)/τ)`
//! after the last change k (target T, position p_k) before t. The DAQ's samples of a stream
//! are evaluated at their own sample times this way, whenever they are read.

use crate::config::Config;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::Distribution;

/// One target change: at bench time `t` (s) the target became `target` (µm) with the sensor
/// at `pos` (µm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Event {
    pub t: f64,
    pub target: f64,
    pub pos: f64,
}

/// Most events kept per axis; older ones are dropped (a read that old is long overwritten).
const EVENTS_CAP: usize = 4_000_000;

/// One axis.
#[derive(Debug, Clone)]
pub struct Axis {
    pub range: f64,
    tau: f64,
    pub events: Vec<Event>,
    /// Last position commanded over USB (`MCL_SingleWriteN`, a load waveform), µm.
    pub usb: f64,
    /// The external input's command, µm (volts / 10 V · range), if it was ever driven.
    pub ext: Option<f64>,
    /// Stuck (fault): the sensor holds this position whatever the target.
    pub stuck_at: Option<f64>,
    /// Where the last search ended ([`Self::index_after`]).
    hint: std::cell::Cell<usize>,
}

impl Axis {
    fn new(range: f64, tau: f64, t: f64) -> Self {
        Axis {
            range,
            tau,
            events: vec![Event {
                t,
                target: 0.0,
                pos: 0.0,
            }],
            usb: 0.0,
            ext: None,
            stuck_at: None,
            hint: std::cell::Cell::new(0),
        }
    }

    /// True sensor position at bench time `t` (µm); before the oldest kept change: the
    /// position then.
    pub fn position_at(&self, t: f64) -> f64 {
        let k = self.index_after(t);
        let e = self.events[k.saturating_sub(1)];
        if k == 0 || self.tau <= 0.0 {
            return if k == 0 { e.pos } else { e.target };
        }
        e.target + (e.pos - e.target) * (-(t - e.t) / self.tau).exp()
    }

    /// The target in force at `t` (µm).
    pub fn target_at(&self, t: f64) -> f64 {
        let k = self.index_after(t);
        self.events[k.saturating_sub(1)].target
    }

    /// The number of changes at or before `t`. A stream's samples are read soon after they
    /// are taken, among the latest changes: those are searched first (a search of millions of
    /// changes per sample made the fake slower than the 800 kS/s it models).
    fn index_after(&self, t: f64) -> usize {
        let e = &self.events;
        let n = e.len();
        if e[n - 1].t <= t {
            return n;
        }
        // the stream's samples come in time order, a change or two apart: step on from the
        // last answer
        let mut h = self.hint.get().min(n);
        if h > 0 && e[h - 1].t <= t {
            for _ in 0..16 {
                if h == n || e[h].t > t {
                    self.hint.set(h);
                    return h;
                }
                h += 1;
            }
        }
        let tail = n.saturating_sub(1 << 14);
        let k = if e[tail].t <= t {
            tail + e[tail..].partition_point(|x| x.t <= t)
        } else {
            e.partition_point(|x| x.t <= t)
        };
        self.hint.set(k);
        k
    }

    /// The target becomes `target` (clamped to the range) at `t` (not before the last change).
    fn retarget(&mut self, t: f64, target: f64) {
        let last = *self.events.last().expect("an axis has at least one event");
        let t = t.max(last.t);
        let target = match self.stuck_at {
            Some(p) => p,
            None => target.clamp(0.0, self.range),
        };
        if target == last.target {
            return;
        }
        let pos = self.position_at(t);
        if self.events.len() >= EVENTS_CAP {
            self.events.drain(..EVENTS_CAP / 2);
        }
        self.events.push(Event { t, target, pos });
    }
}

/// The Nano-Drive controller with its stage, as Madlib sees it.
pub struct NanoDrive {
    pub axes: [Axis; 3],
    pub serial: i32,
    ext_sum: bool,
    noise_um: f64,
    rng: ChaCha8Rng,
}

/// `ProductInformation.Product_id` of a Nano-Drive three-axis 16-bit controller (0x2003, as
/// listed in MCL's published Madlib wrappers' `MCL_GrabHandle` device table).
pub const PRODUCT_ID: i16 = 0x2003;
/// Firmware version and profile reported (profile bits: 0x0008 commanded position, 0x0010
/// waveforms, 0x0100 sequences, as MCL's examples document the bits).
pub const FIRMWARE_VERSION: i16 = 3;
pub const FIRMWARE_PROFILE: i16 = 0x0118;

impl NanoDrive {
    pub fn new(cfg: &Config, t: f64) -> Self {
        let mut d = NanoDrive {
            axes: [
                Axis::new(cfg.range_um[0], cfg.tau_s, t),
                Axis::new(cfg.range_um[1], cfg.tau_s, t),
                Axis::new(cfg.range_um[2], cfg.tau_s, t),
            ],
            serial: cfg.serial,
            ext_sum: cfg.ext_sum,
            noise_um: cfg.sensor_noise_um,
            rng: ChaCha8Rng::seed_from_u64(cfg.seed ^ 0x5EED_57A6E),
        };
        d.apply_stuck(&cfg.faults.stage_stuck, t);
        d
    }

    /// Apply the stuck-axis fault switches at `t`.
    pub fn apply_stuck(&mut self, stuck: &[bool; 3], t: f64) {
        for (a, &s) in self.axes.iter_mut().zip(stuck) {
            if s && a.stuck_at.is_none() {
                let p = a.position_at(t);
                a.stuck_at = Some(p);
                a.retarget(t, p);
            } else if !s && a.stuck_at.is_some() {
                a.stuck_at = None;
            }
        }
    }

    fn physical_target(&self, i: usize, src_ext: bool) -> f64 {
        let a = &self.axes[i];
        if self.ext_sum {
            a.usb + a.ext.unwrap_or(0.0)
        } else if src_ext {
            a.ext.unwrap_or(0.0)
        } else {
            a.usb
        }
    }

    /// A USB command (`MCL_SingleWriteN`, a load waveform point) to axis `i` (0-based) at `t`.
    pub fn command(&mut self, i: usize, t: f64, um: f64) {
        self.axes[i].usb = um;
        let target = self.physical_target(i, false);
        self.axes[i].retarget(t, target);
    }

    /// The external input of axis `i` at `volts` from `t` on (0–10 V over the range).
    pub fn external(&mut self, i: usize, t: f64, volts: f64) {
        let um = volts.clamp(0.0, 10.0) / 10.0 * self.axes[i].range;
        if self.axes[i].ext == Some(um) {
            return;
        }
        self.axes[i].ext = Some(um);
        let target = self.physical_target(i, true);
        self.axes[i].retarget(t, target);
    }

    /// A sensor reading of axis `i` at `t` (µm): the position plus the sensor's noise,
    /// quantised to the 16-bit ADC's step (range / 65535).
    pub fn read(&mut self, i: usize, t: f64) -> f64 {
        let p = self.axes[i].position_at(t) + self.noise();
        let step = self.axes[i].range / 65535.0;
        ((p / step).round() * step).clamp(0.0, self.axes[i].range)
    }

    /// The sensor monitor's voltage of axis `i` at `t` (0–10 V over the range, with the
    /// sensor's noise).
    pub fn monitor_v(&mut self, i: usize, t: f64) -> f64 {
        let p = self.axes[i].position_at(t) + self.noise();
        p / self.axes[i].range * 10.0
    }

    fn noise(&mut self) -> f64 {
        if self.noise_um > 0.0 {
            let z: f64 = rand_distr::StandardNormal.sample(&mut self.rng);
            z * self.noise_um
        } else {
            0.0
        }
    }

    /// True positions of the three axes at `t` (µm).
    pub fn position(&self, t: f64) -> [f64; 3] {
        [
            self.axes[0].position_at(t),
            self.axes[1].position_at(t),
            self.axes[2].position_at(t),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn drive(tau_ms: f64) -> NanoDrive {
        let c = Config {
            tau_s: tau_ms / 1e3,
            sensor_noise_um: 0.0,
            ..Config::default()
        };
        NanoDrive::new(&c, 0.0)
    }

    #[test]
    fn first_order_lag_closed_form() {
        let mut d = drive(2.0);
        d.command(0, 1.0, 10.0);
        // p(t) = 10 (1 − exp(−(t − 1)/τ))
        for dt in [0.0, 0.001, 0.002, 0.006] {
            let want = 10.0 * (1.0 - (-dt / 0.002f64).exp());
            assert!((d.axes[0].position_at(1.0 + dt) - want).abs() < 1e-12);
        }
        // a second target mid-way starts from the position then
        d.command(0, 1.002, 0.0);
        let p1 = 10.0 * (1.0 - (-1.0f64).exp());
        let want = p1 * (-0.5f64).exp();
        assert!((d.axes[0].position_at(1.003) - want).abs() < 1e-12);
        // the past is unchanged
        assert!((d.axes[0].position_at(1.001) - 10.0 * (1.0 - (-0.5f64).exp())).abs() < 1e-12);
    }

    #[test]
    fn clamps_external_and_override() {
        let c = Config {
            tau_s: 0.0,
            sensor_noise_um: 0.0,
            ext_sum: false,
            ..Config::default()
        };
        let mut d = NanoDrive::new(&c, 0.0);
        d.command(0, 0.0, 200.0);
        assert_eq!(d.axes[0].position_at(0.1), 75.0);
        d.external(0, 0.2, 4.0);
        assert_eq!(d.axes[0].position_at(0.3), 30.0);
        d.external(0, 0.4, -3.0);
        assert_eq!(d.axes[0].position_at(0.5), 0.0);
        d.command(0, 0.6, 12.0);
        assert_eq!(d.axes[0].position_at(0.7), 12.0);
    }

    /// The default controller sums: 37 µm over USB plus 37 µm on the external input is the
    /// end of the 75 µm travel (clamped), and the external input at 0 V gives the USB command.
    #[test]
    fn the_default_controller_adds_the_external_input_to_the_usb_command() {
        let mut d = drive(0.0);
        d.command(0, 0.0, 37.0);
        assert_eq!(d.axes[0].position_at(0.1), 37.0);
        d.external(0, 0.2, 37.0 / 75.0 * 10.0);
        assert_eq!(d.axes[0].position_at(0.3), 74.0);
        d.external(0, 0.4, 6.0);
        assert_eq!(d.axes[0].position_at(0.5), 75.0);
        d.command(0, 0.6, 0.0);
        assert_eq!(d.axes[0].position_at(0.7), 45.0);
        d.external(0, 0.8, 0.0);
        assert_eq!(d.axes[0].position_at(0.9), 0.0);
    }

    #[test]
    fn stuck_axis_stays() {
        let mut d = drive(1.0);
        d.command(1, 0.0, 5.0);
        d.apply_stuck(&[false, true, false], 1.0);
        d.command(1, 1.0, 50.0);
        assert!((d.axes[1].position_at(2.0) - 5.0).abs() < 1e-9);
        assert_eq!(d.axes[1].usb, 50.0);
    }
}
