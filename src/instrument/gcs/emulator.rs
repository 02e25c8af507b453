//! A PI GCS 2.0 piezo controller emulator: three closed-loop axes with a travel range, servo
//! state, settle dynamics and GCS's single error register (`ERR?` returns the last error and
//! clears it).
//!
//! Motion as PI's documents describe it: the trajectory ramps linearly from where the axis was
//! to the target over the settle time, and `#5` (motion status) reports the axis in motion
//! while the trajectory runs; `ONT?` (on target) is the E-727 manual's rule: the position has
//! been inside the settling window (parameter 0x07000900, "On Target Tolerance") for at least
//! the settling time (0x07000901), so `ONT?` can still answer 0 when `#5` already answers 0.
//! `SPA`/`SPA?` read and set both parameters per axis.
//!
//! Commands: `#5` (motion status), `#7` (ready), `#24` (stop) as single characters, `*IDN?`, `ERR?`, `SAI?`, `SAI? ALL`, `SVO`, `SVO?`, `MOV`, `MOV?`, `POS?`,
//! `ONT?`, `TMN?`, `TMX?`, `VEL`, `VEL?`, `STP`, `HLT`. Queries take an optional axis list (all
//! axes without one). Errors: 1 parameter syntax, 2 unknown command, 5 servo off, 7 position
//! out of limits, 10 stopped, 15 invalid axis identifier.
//!
//! The wave generator (`WAV` `LIN`/`RAMP`/`PNT`, `WAV?`, `WSL`, `WGC`, `WTR`, `WGO`, their
//! queries and `#9`), the trigger outputs (`CTO`, `CTO?`, `TWS`, `TWC`) and the data recorder
//! (`DRC`, `DRC?`, `DRT`, `DRT?`, `RTR`, `RTR?`, `DRL?`, `DRR?`) run under the controller's
//! servo clock: see [`WaveConfig`] and the `wave` module (stage/wave.rs). `STP`, `HLT` and `#24` stop
//! the generators too; `MOV`/`SVO` on an axis whose generator runs are refused (error 73).
//!
//! `SAI?` as PI documents it: the identifiers of the configured (active) axes, one per line
//! (`1 ␠\n2 ␠\n3\n`); `SAI? ALL` also lists deactivated axes ([`StageEmulatorConfig::inactive_axes`]).
//! With [`StageEmulatorConfig::one_axis_per_query`] the emulator behaves like a controller that
//! answers a query naming several axes for the first one only.

use crate::instrument::emulation::{
    lock, pty_line, spawn, tcp_line, Device, Emulator, Faults, LinkModel, SharedPosition,
};
mod wave;
mod wave_state;
use crate::instrument::Pos;
use std::sync::{Arc, Mutex};
use std::time::Instant;
pub use wave_state::WaveConfig;

/// Stage emulator settings.
#[derive(Debug, Clone, PartialEq)]
pub struct StageEmulatorConfig {
    /// Axis identifiers for x, y, z (an E-727: `1 2 3`).
    pub axes: [String; 3],
    /// Deactivated axes: listed by `SAI? ALL` only, not by `SAI?`, and refused (error 15)
    /// elsewhere.
    pub inactive_axes: Vec<String>,
    /// A query naming several axes (`POS? 1 2 3`) is answered for the first axis only, as by
    /// controllers that take one axis per query.
    pub one_axis_per_query: bool,
    /// Travel range (min, max) per axis, µm.
    pub travel: [(f64, f64); 3],
    /// Position at power-on, µm (clamped into the travel range).
    pub start: Pos,
    /// Time to settle on a new target, s (linear ramp).
    pub settle_s: f64,
    /// Settling window, µm: `ONT?` reports 1 once the position has been within this distance
    /// of the target for `settling_time_s` (E-727 parameter 0x07000900).
    pub on_target_window_um: f64,
    /// Settling time, s (E-727 parameter 0x07000901): how long the position must stay inside
    /// the settling window before `ONT?` reports 1.
    pub settling_time_s: f64,
    /// Servo state at power-on.
    pub servo_on: bool,
    /// `*IDN?` reply.
    pub idn: String,
    /// Initial fault switches.
    pub faults: Faults,
    /// Answer PI's single-character commands `#5` (motion status), `#7` (ready) and `#24`
    /// (stop). False: a controller without them (they set error 2, "Unknown command", and
    /// get no reply).
    pub single_char_commands: bool,
    /// The serial link modelled (baud rate, reply latency); default the pty's full speed.
    pub link: LinkModel,
    /// Wave generator, data recorder and trigger outputs (servo clock, axis lag, sizes, and
    /// what OUT1…OUT3 are wired to).
    pub wave: WaveConfig,
}

impl Default for StageEmulatorConfig {
    /// A P-517.3CD-like stage on an E-727: 100 × 100 × 20 µm, parked at the origin.
    fn default() -> Self {
        Self {
            axes: ["1".into(), "2".into(), "3".into()],
            inactive_axes: Vec::new(),
            one_axis_per_query: false,
            travel: [(0.0, 100.0), (0.0, 100.0), (0.0, 20.0)],
            start: [0.0; 3],
            settle_s: 0.002,
            on_target_window_um: 0.001,
            settling_time_s: 0.0,
            servo_on: false,
            idn: "(c)2026 Physik Instrumente (PI) GmbH & Co. KG, E-727, 0000000000, 1.0.0 (bfpscope emulator)"
                .into(),
            faults: Faults::default(),
            single_char_commands: true,
            link: LinkModel::FULL_SPEED,
            wave: WaveConfig::default(),
        }
    }
}

impl StageEmulatorConfig {
    /// A stage like the simulator's: same travel range and move time, parked at the origin.
    pub fn like_sim(sim: &crate::instrument::sim::SimConfig) -> Self {
        Self {
            travel: sim.travel,
            settle_s: sim.move_time_s,
            ..Self::default()
        }
    }
}

struct Axis {
    from: f64,
    target: f64,
    t0: Instant,
    servo: bool,
    /// The servo tripped (error −1024): the axis stays at `from`, off target.
    tripped: bool,
    /// Settle time of the move under way, s, fixed when it was commanded (a later change of
    /// `Faults::settle_s` applies to later moves).
    settle: f64,
    /// Under the wave generator's first-order lag model: the current position, µm (until the
    /// next `MOV` or stop).
    lag: Option<f64>,
}

struct GcsDevice {
    cfg: StageEmulatorConfig,
    axes: [Axis; 3],
    error: i64,
    faults: Arc<Mutex<Faults>>,
    position: SharedPosition,
    /// State of the sensor-noise generator (`Faults::pos_noise_um`).
    noise_state: std::cell::Cell<u64>,
    /// Closed-loop velocity per axis (`VEL`), units/s: stored and reported (`VEL?`); the
    /// emulated motion keeps its settle-time ramp.
    velocity: [f64; 3],
    /// Wave generator, recorder, trigger outputs.
    wave: wave_state::Wave,
    /// Settling window (µm) and settling time (s) per axis (`SPA` 0x07000900, 0x07000901).
    window_um: [f64; 3],
    settling_s: [f64; 3],
}

impl GcsDevice {
    /// Deterministic noise, uniform in [−1, 1] (a 64-bit LCG, Knuth's MMIX constants).
    fn next_noise(&self) -> f64 {
        let s = self
            .noise_state
            .get()
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        self.noise_state.set(s);
        (s >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }

    fn settle(&self) -> f64 {
        lock(&self.faults)
            .settle_s
            .unwrap_or(self.cfg.settle_s)
            .max(0.0)
    }

    /// Position and on-target flag of axis `i` now: on target once the position has been
    /// inside the settling window for the settling time (E-727: `ONT?`).
    fn axis_now(&self, i: usize, now: Instant) -> (f64, bool) {
        let a = &self.axes[i];
        let window = self.window_um[i];
        if a.tripped {
            return (a.from, false);
        }
        if let Some(x) = a.lag {
            let on = !self.wave.running(i) && (x - a.target).abs() <= window;
            return (x, on);
        }
        let since = now.duration_since(a.t0).as_secs_f64();
        let f = if a.settle > 0.0 {
            since / a.settle
        } else {
            1.0
        };
        let p = if f >= 1.0 {
            a.target
        } else {
            a.from + (a.target - a.from) * f
        };
        // the instant (s after the MOV) the linear trajectory entered the window, for good
        let d = (a.target - a.from).abs();
        let entered = if a.settle > 0.0 && d > window {
            a.settle * (1.0 - window / d)
        } else {
            0.0
        };
        let settling = lock(&self.faults)
            .settling_time_s
            .unwrap_or(self.settling_s[i])
            .max(0.0);
        (
            p,
            since >= entered + settling && (p - a.target).abs() <= window,
        )
    }

    /// Axis `i`'s trajectory runs (`#5`: "axis in motion"): the ramp to the target has not
    /// ended, or the wave generator drives it.
    fn in_motion(&self, i: usize, now: Instant) -> bool {
        let a = &self.axes[i];
        if a.tripped {
            return false;
        }
        if a.lag.is_some() {
            return self.wave.running(i);
        }
        a.settle > 0.0 && now.duration_since(a.t0).as_secs_f64() < a.settle
    }

    fn positions(&self) -> ([f64; 3], [bool; 3]) {
        self.positions_at(Instant::now())
    }

    fn positions_at(&self, now: Instant) -> ([f64; 3], [bool; 3]) {
        let mut p = [0.0; 3];
        let mut o = [false; 3];
        for i in 0..3 {
            (p[i], o[i]) = self.axis_now(i, now);
        }
        (p, o)
    }

    fn set_error(&mut self, code: i64) {
        // GCS keeps only the last error.
        self.error = code;
    }

    /// Axis indices named in `args` (all axes if none). Error 15 for an unknown name.
    fn axis_list(&mut self, args: &[&str]) -> Option<Vec<usize>> {
        if args.is_empty() {
            return Some(vec![0, 1, 2]);
        }
        let mut v = Vec::new();
        for a in args {
            match self.cfg.axes.iter().position(|n| n == a) {
                Some(i) => v.push(i),
                None => {
                    self.set_error(15);
                    return None;
                }
            }
        }
        Some(v)
    }

    /// `AXIS value AXIS value …` pairs. Error 1 for a malformed list, 15 for an unknown axis.
    fn pairs(&mut self, args: &[&str]) -> Option<Vec<(usize, f64)>> {
        let Ok(groups) = groups::<2>(args) else {
            self.set_error(1);
            return None;
        };
        let mut v = Vec::new();
        for c in groups {
            let Some(i) = self.cfg.axes.iter().position(|n| n == c[0]) else {
                self.set_error(15);
                return None;
            };
            match c[1].parse::<f64>() {
                Ok(x) if x.is_finite() => v.push((i, x)),
                _ => {
                    self.set_error(1);
                    return None;
                }
            }
        }
        Some(v)
    }

    /// A multi-line `AXIS=value` reply: every line but the last ends with a space.
    fn reply(&self, idx: &[usize], f: impl Fn(usize) -> String) -> String {
        let lines: Vec<String> = idx
            .iter()
            .map(|&i| format!("{}={}", self.cfg.axes[i], f(i)))
            .collect();
        lines.join(" \n")
    }

    fn publish(&self) {
        let (p, _) = self.positions();
        *lock(&self.position) = p;
    }

    fn halt(&mut self) {
        self.advance(Instant::now());
        self.wave.stop_all();
        let (p, _) = self.positions();
        let now = Instant::now();
        for (a, x) in self.axes.iter_mut().zip(p) {
            a.from = x;
            a.target = x;
            a.t0 = now;
            a.tripped = false;
            a.lag = None;
        }
        self.set_error(10);
    }
}

impl GcsDevice {
    /// `SAI?` (`SAI? ALL`: with the inactive axes), or error 1 for other arguments.
    fn sai(&mut self, args: &[&str]) -> Option<String> {
        let mut ids = self.cfg.axes.to_vec();
        match args {
            [] => {}
            [all] if all.eq_ignore_ascii_case("ALL") => {
                ids.extend(self.cfg.inactive_axes.iter().cloned())
            }
            _ => {
                self.set_error(1);
                return None;
            }
        }
        Some(ids.join(" \n"))
    }

    /// `#5`'s answer: the hexadecimal bit mask of the axes in motion.
    fn motion_mask(&self) -> String {
        let now = Instant::now();
        let mask = (0..3)
            .filter(|&i| self.in_motion(i, now))
            .fold(0u32, |m, i| m | (1 << i));
        format!("{mask:X}")
    }
}

impl Device for GcsDevice {
    fn tick(&mut self) {
        self.advance(Instant::now());
        self.publish();
    }

    fn is_error_query(&self, line: &str) -> bool {
        line.trim().eq_ignore_ascii_case("ERR?")
    }

    fn single_char(&self, byte: u8) -> Option<&'static str> {
        match byte {
            0x05 => Some("#5"),
            0x07 => Some("#7"),
            0x18 => Some("#24"),
            0x09 => Some("#9"),
            _ => None,
        }
    }

    fn inject_error(&mut self, code: i64) {
        self.set_error(code);
    }

    fn handle(&mut self, line: &str) -> Option<String> {
        let mut words = line.split_whitespace();
        let cmd = words.next()?.to_ascii_uppercase();
        let args: Vec<&str> = words.collect();
        self.advance(Instant::now());
        if let Some(reply) = self.wave_command(&cmd, &args) {
            self.publish();
            return reply;
        }
        let reply = match cmd.as_str() {
            "#5" | "#7" | "#9" | "#24" if !self.cfg.single_char_commands => {
                self.set_error(2);
                None
            }
            // #5, motion status: a hexadecimal bit mask of the axes in motion, bit 0 the first
            // axis of `SAI?` (PI: "1 = first axis in motion, 2 = second, 4 = third"): the
            // trajectory, not the settling window (that is `ONT?`); a tripped axis has stopped.
            "#5" => Some(self.motion_mask()),
            // #7, controller ready: 0xB1 ("±" in ISO 8859-1) ready, 0xB0 not ready; a piezo
            // controller is ready for the next command at once
            "#7" => Some("\u{b1}".to_string()),
            "#24" => {
                self.halt();
                None
            }
            "*IDN?" => Some(self.cfg.idn.clone()),
            "SAI?" => self.sai(&args),
            "ERR?" => {
                let e = self.error;
                self.error = 0;
                Some(e.to_string())
            }
            "VEL" => {
                let pairs = self.pairs(&args)?;
                if pairs.iter().any(|&(_, v)| v.is_nan() || v <= 0.0) {
                    self.set_error(1);
                    return None;
                }
                for (i, v) in pairs {
                    self.velocity[i] = v;
                }
                None
            }
            "VEL?" => {
                let mut idx = self.axis_list(&args)?;
                if self.cfg.one_axis_per_query {
                    idx.truncate(1);
                }
                let v = self.velocity;
                Some(self.reply(&idx, |i| format!("{:.6}", v[i])))
            }
            "POS?" | "ONT?" | "TMN?" | "TMX?" | "SVO?" | "MOV?" => {
                let mut idx = self.axis_list(&args)?;
                if self.cfg.one_axis_per_query {
                    idx.truncate(1);
                }
                let (p, ont) = self.positions();
                let t = self.cfg.travel;
                Some(match cmd.as_str() {
                    "POS?" => {
                        let noise = lock(&self.faults).pos_noise_um;
                        let p = p.map(|v| v + noise * self.next_noise());
                        self.reply(&idx, |i| format!("{:.6}", p[i]))
                    }
                    "ONT?" => self.reply(&idx, |i| u8::from(ont[i]).to_string()),
                    "TMN?" => self.reply(&idx, |i| format!("{:.6}", t[i].0)),
                    "TMX?" => self.reply(&idx, |i| format!("{:.6}", t[i].1)),
                    "SVO?" => self.reply(&idx, |i| u8::from(self.axes[i].servo).to_string()),
                    _ => self.reply(&idx, |i| format!("{:.6}", self.axes[i].target)),
                })
            }
            "SVO" => {
                let pairs = self.pairs(&args)?;
                if pairs.iter().any(|&(_, v)| v != 0.0 && v != 1.0) {
                    self.set_error(1);
                    return None;
                }
                if pairs.iter().any(|&(i, _)| self.wave.running(i)) {
                    self.set_error(73);
                    return None;
                }
                for (i, v) in pairs {
                    let a = &mut self.axes[i];
                    a.servo = v == 1.0;
                    if a.servo && a.tripped {
                        // servo back on: it holds where the axis stopped
                        a.tripped = false;
                        a.target = a.from;
                    }
                }
                None
            }
            "MOV" => {
                let pairs = self.pairs(&args)?;
                if pairs.iter().any(|&(i, _)| !self.axes[i].servo) {
                    self.set_error(5);
                    return None;
                }
                if pairs.iter().any(|&(i, _)| self.wave.running(i)) {
                    self.set_error(73);
                    return None;
                }
                let reject = lock(&self.faults).reject_out_of_range;
                let t = self.cfg.travel;
                if reject && pairs.iter().any(|&(i, v)| v < t[i].0 || v > t[i].1) {
                    self.set_error(7);
                    return None;
                }
                let (p, _) = self.positions();
                let now = Instant::now();
                let trip = std::mem::take(&mut lock(&self.faults).servo_trip_next_move);
                let settle = self.settle();
                for (i, v) in pairs {
                    let a = &mut self.axes[i];
                    a.from = p[i];
                    a.target = v.clamp(t[i].0, t[i].1);
                    a.t0 = now;
                    a.settle = settle;
                    a.lag = None;
                    if trip {
                        a.tripped = true;
                        a.servo = false;
                    }
                }
                if trip {
                    self.set_error(-1024);
                }
                self.wave.clear_path();
                self.wave.position_command();
                None
            }
            "STP" | "HLT" => {
                self.halt();
                None
            }
            _ => {
                self.set_error(2);
                None
            }
        };
        self.publish();
        reply
    }
}

/// Start a GCS stage emulator on a new pseudo-terminal. `position` is updated with the
/// emulated position (µm) as the stage moves (share it with a QPD emulator).
pub fn start_stage_emulator(
    cfg: StageEmulatorConfig,
    position: SharedPosition,
) -> std::io::Result<Emulator> {
    let link = cfg.link;
    let (dev, faults) = device(cfg, position.clone())?;
    spawn("stage", dev, faults, position, pty_line()?, link)
}

/// As [`start_stage_emulator`], served on a TCP port as a PI controller's GCS port is: `addr`
/// such as `127.0.0.1:0` (a free port); [`Emulator::path`] is `tcp://127.0.0.1:PORT`, which is
/// also what `[stage] port` takes. One client at a time; the next may connect when it leaves.
pub fn start_stage_emulator_tcp(
    cfg: StageEmulatorConfig,
    position: SharedPosition,
    addr: &str,
) -> std::io::Result<Emulator> {
    let link = cfg.link;
    let (dev, faults) = device(cfg, position.clone())?;
    spawn("stage", dev, faults, position, tcp_line(addr)?, link)
}

/// The `{<axis> <value>}` (`MOV`), `{<item> <id> <value>}` (`SPA`) … groups of `N` arguments a
/// GCS command takes: GCS error 1 (parameter syntax) unless there is at least one group and
/// nothing is left over.
fn groups<'a, 'b, const N: usize>(args: &'a [&'b str]) -> Result<&'a [[&'b str; N]], i64> {
    match args.as_chunks::<N>() {
        (g, []) if !g.is_empty() => Ok(g),
        _ => Err(1),
    }
}

fn device(
    cfg: StageEmulatorConfig,
    position: SharedPosition,
) -> std::io::Result<(GcsDevice, Arc<Mutex<Faults>>)> {
    let now = Instant::now();
    let mut axes = Vec::new();
    for i in 0..3 {
        let (lo, hi) = cfg.travel[i];
        let x = cfg.start[i].clamp(lo.min(hi), hi.max(lo));
        axes.push(Axis {
            from: x,
            target: x,
            t0: now,
            servo: cfg.servo_on,
            tripped: false,
            settle: 0.0,
            lag: None,
        });
    }
    let axes: [Axis; 3] = axes
        .try_into()
        .map_err(|_| std::io::Error::other("three axes"))?;
    let faults = Arc::new(Mutex::new(cfg.faults.clone()));
    let cfg_wave = cfg.wave.clone();
    let (cfg_window, cfg_settling) = (cfg.on_target_window_um, cfg.settling_time_s.max(0.0));
    let dev = GcsDevice {
        cfg,
        axes,
        error: 0,
        faults: faults.clone(),
        position,
        noise_state: std::cell::Cell::new(0x5eed),
        velocity: [10_000.0; 3],
        wave: wave_state::Wave::new(cfg_wave, now),
        window_um: [cfg_window; 3],
        settling_s: [cfg_settling; 3],
    };
    dev.publish();
    Ok((dev, faults))
}
