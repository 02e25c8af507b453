//! The GCS stage emulator's wave generator, trigger output and data recorder, run under the
//! controller's own servo clock.
//!
//! Sources: PI's public GCS 2.0 command descriptions (E-727 user manual E727T0005: `CTO`
//! trigger modes and `<CTOPam>` IDs, wave generator and `TWS`, `WOS`; C-863 manual MS249E:
//! `DRR?`, `DRL?`) and PIPython's documentation of the same commands (`gcsbasecommands.py`:
//! argument order of `WAV … LIN/RAMP/PNT`, `WSL`, `WGC`, `WGO`, `WTR`, `CTO`, `DRC`, `RTR`,
//! `DRR?`; `gcs2datarectools.py`: record options and trigger sources; `gcsmessages.py` and
//! `gcsbasepitools.py`: the GCS array format of `DRR?`, header lines `# KEY = VALUE`, a
//! `# END_HEADER` line, data rows separated by `SEPARATOR`, every line but the last ending in
//! a space).
//!
//! Model (all times in servo cycles of [`WaveConfig::servo_cycle_s`](super::wave_state::WaveConfig::servo_cycle_s)):
//! - wave tables hold absolute positions (µm): PI's sample `wavegenerator_pnt.py` moves the
//!   axis to the first wave point before `WGO`, and the E-727 manual gives "generator output =
//!   current wave value (+ `WOS` offset)"; `WOS` is not emulated (offset 0);
//! - wave generator n drives axis n (the n-th axis of `SAI?`); a running generator outputs
//!   point `⌊j / rate⌋ mod length` of its table at servo cycle `j` after the start (`WTR` rate;
//!   interpolation is accepted and not applied) for `WGC` cycles (0 = until `WGO n 0`), then
//!   holds its last value;
//! - an axis driven by a generator follows its target with a first-order lag of time constant
//!   τ = [`WaveConfig::lag_s`](super::wave_state::WaveConfig::lag_s): per cycle `x += α·(target − x)`, `α = 1 − exp(−dt/τ)`, the
//!   discrete form of a closed-loop piezo with bandwidth `1/(2πτ)`. On a ramp of speed `v`
//!   the recorded position trails the target by `v·dt/(exp(dt/τ) − 1)` ≈ `v·(τ − dt/2)`. The
//!   axis keeps the lag model until the next `MOV` or `STP`;
//! - the data recorder samples every `RTR` cycles, starting at the cycle its trigger fires;
//!   trigger sources (`DRT`): 0 default = a generator start (`WGO`), 1 = any command that
//!   changes a position (`MOV`, `WGO`), 4 = immediately; each table stores one record option
//!   of one axis (`DRC`): 0 nothing, 1 target position, 2 current position, 3 position error
//!   (target − current), µm;
//! - trigger outputs OUT1…OUT3 (`CTO`): `<CTOPam>` 1 TriggerStep, 2 Axis, 3 TriggerMode, 5
//!   MinThreshold, 6 MaxThreshold, 7 Polarity, 8 StartThreshold, 9 StopThreshold; modes 0
//!   position distance (a pulse every TriggerStep of travel; with StartThreshold ≠
//!   StopThreshold only from start to stop, in that direction), 2 on target, 3 min/max band,
//!   4 generator trigger (the line level set per wave point with `TWS <line> <point> <switch>`,
//!   switch 0 = low, 1 = high; point 1 = the first point of the axis' generator). Each rising
//!   edge of the (polarity-corrected) line is one pulse on the [`ExtTrigger`](crate::instrument::emulation::ExtTrigger) wired to it.
//!
//! - parameters (`SPA? <item> <id>`, E-727 parameter list; PIPython's `getservotime` and
//!   `getmaxnumvalues` read them): 0x0E000200 Servo Update Time (s), 0x16000200 Data Recorder
//!   Max Points (all tables), 0x16000300 Data Recorder Chan Number, 0x07000900 settling window
//!   (µm) and 0x07000901 settling time (s), both also set with `SPA`; `WMS? [<table> …]`: points
//!   per wave table (PI's "maximum size of the wave storage");
//! - the path of a running wave is published at `WGO` on [`WaveConfig::path`](super::wave_state::WaveConfig::path) (see
//!   [`StagePath`](crate::instrument::emulation::StagePath)), truncated at `WGO g 0`, `STP`, `HLT`, `#24`, cleared by `MOV`; trigger
//!   pulses carry the instant of their servo cycle ([`ExtTrigger::pulse_at`](crate::instrument::emulation::ExtTrigger::pulse_at)).
//!
//! Errors (GCS codes): 1 syntax, 5 servo off, 7 wave outside the travel range, 15 unknown axis,
//! 17 an id or value out of range, 54 a parameter not emulated, 57 no such record table, 58 no
//! such record option, 59 no such record source, 67 wave table full, 73 motion command or wave
//! change while a generator runs, 75 `WGO` without a wave table, 77 `DRR?` of points not yet
//! recorded.

use super::wave_state::{Rec, TrigLine, Wave};
use super::{groups, GcsDevice};
use crate::instrument::emulation::PathData;
use crate::instrument::line::lin_point;
use std::time::Instant;

fn parse_u(s: &str) -> Option<u64> {
    s.parse::<u64>().ok()
}

fn parse_f(s: &str) -> Option<f64> {
    s.parse::<f64>().ok().filter(|v| v.is_finite())
}

/// Trapezoidal line from 0 to `amp` over `n` points with `s` points of constant acceleration
/// at each end (PI's speed-up/down; its exact shape is not public).
fn lin_curve(amp: f64, n: usize, s: usize) -> Vec<f64> {
    if n <= 1 {
        return vec![amp; n];
    }
    (0..n).map(|i| lin_point(amp, n, s, i)).collect()
}

/// Most servo cycles a published path holds (about 3.5 min at 50 µs).
const MAX_PATH_CYCLES: usize = 1 << 22;

impl GcsDevice {
    /// Publish the path of the generators just started (`WGO`), computed as
    /// [`servo_cycle`](Self::servo_cycle) will compute it: the generator's output per cycle,
    /// the lag `x += α·(target − x)`, then `10 τ` more cycles for the lag to settle on the
    /// last point (after that the path holds its last value).
    fn publish_path(&mut self, now: Instant) {
        let Some(handle) = self.wave.cfg.path.clone() else {
            return;
        };
        let (base, _) = self.positions_at(now);
        let dt = self.wave.dt();
        let tail = (10.0 * self.wave.cfg.lag_s / dt).ceil() as usize + 1;
        let mut start = None;
        let mut x: [Option<Vec<f64>>; 3] = [None, None, None];
        for (i, xi) in x.iter_mut().enumerate() {
            let g = &self.wave.gens[i];
            if !g.running {
                continue;
            }
            start = Some(start.map_or(g.start, |s: u64| s.min(g.start)));
            let table = &self.wave.tables[g.table - 1];
            let len = table.len().max(1);
            let rate = g.rate.max(1) as usize;
            let wave_cycles = if g.cycles == 0 {
                MAX_PATH_CYCLES
            } else {
                (len * rate).saturating_mul(g.cycles as usize)
            };
            let n = wave_cycles.saturating_add(tail).min(MAX_PATH_CYCLES);
            let mut p = self.axes[i].lag.unwrap_or(base[i]);
            let mut target = self.axes[i].target;
            let mut v = Vec::with_capacity(n);
            for j in 0..n {
                if j < wave_cycles {
                    target = table[(j / rate) % len];
                }
                p += self.wave.alpha * (target - p);
                v.push(p);
            }
            *xi = Some(v);
        }
        if let Some(k0) = start {
            handle.set(PathData {
                start: self.wave.instant_of(k0),
                dt,
                base,
                x,
                stop: None,
            });
        }
    }

    /// Advance the servo clock to `now`: generator outputs, lagged axes, trigger outputs and
    /// the recorder, cycle by cycle.
    pub(super) fn advance(&mut self, now: Instant) {
        let target = self.wave.cycle_at(now);
        let lagging = self.axes.iter().any(|a| {
            a.lag
                .is_some_and(|x| (x - a.target).abs() > 1e-12 * (1.0 + a.target.abs()))
        });
        if !self.wave.busy(lagging) {
            self.wave.cycle = self.wave.cycle.max(target);
            return;
        }
        while self.wave.cycle < target {
            self.wave.cycle += 1;
            let k = self.wave.cycle;
            self.servo_cycle(k);
        }
    }

    fn servo_cycle(&mut self, k: u64) {
        let t = self.wave.instant_of(k);
        let mut x = [0.0; 3];
        let mut tgt = [0.0; 3];
        for i in 0..3 {
            let g = &mut self.wave.gens[i];
            if g.running && k >= g.start {
                let table = &self.wave.tables[g.table - 1];
                let idx = ((k - g.start) / u64::from(g.rate.max(1))) as usize;
                let len = table.len().max(1);
                if g.cycles > 0 && idx / len >= g.cycles as usize {
                    g.running = false;
                } else {
                    g.point = idx % len;
                    self.axes[i].target = table[g.point];
                }
            }
            if let Some(p) = self.axes[i].lag {
                let a = &mut self.axes[i];
                let p = p + self.wave.alpha * (a.target - p);
                a.lag = Some(p);
                x[i] = p;
                tgt[i] = a.target;
            } else {
                x[i] = self.axis_now(i, t).0;
                tgt[i] = self.axes[i].target;
            }
        }
        // trigger outputs
        for li in 0..3 {
            let Some(out) = self.wave.cfg.trigger_out[li].clone() else {
                continue;
            };
            let on_target = {
                let a = &self.axes[self.wave.lines[li].axis];
                !self.wave.gens[self.wave.lines[li].axis].running
                    && (x[self.wave.lines[li].axis] - a.target).abs()
                        <= self.window_um[self.wave.lines[li].axis]
            };
            let gen_point = {
                let ax = self.wave.lines[li].axis;
                let g = &self.wave.gens[ax];
                (g.running && k >= g.start).then_some(g.point + 1)
            };
            let l = &mut self.wave.lines[li];
            let xi = x[l.axis];
            let pulse = match l.mode {
                Some(0) => {
                    let mut fire = false;
                    if l.step > 0.0 {
                        if l.start != l.stop {
                            let dir = (l.stop - l.start).signum();
                            if let (None, Some(prev)) = (l.next, l.last_x) {
                                if (prev - l.start) * dir < 0.0 && (xi - l.start) * dir >= 0.0 {
                                    fire = true;
                                    l.next = Some(l.start + dir * l.step);
                                }
                            } else if let Some(n) = l.next {
                                if (xi - n) * dir >= 0.0 && (n - l.stop) * dir <= 0.0 {
                                    fire = true;
                                    l.next = Some(n + dir * l.step);
                                }
                                if (xi - l.stop) * dir > 0.0 {
                                    l.next = None;
                                }
                            }
                        } else {
                            let reference = *l.next.get_or_insert(xi);
                            if (xi - reference).abs() >= l.step {
                                fire = true;
                                l.next = Some(xi);
                            }
                        }
                    }
                    fire
                }
                Some(m @ (2..=4)) => {
                    let level = match m {
                        2 => on_target,
                        3 => xi >= l.min && xi <= l.max,
                        _ => gen_point.is_some_and(|p| {
                            l.tws.range(..=p).next_back().is_some_and(|(_, &v)| v)
                        }),
                    };
                    let level = if l.polarity == 0 { !level } else { level };
                    let rising = level && !l.level;
                    l.level = level;
                    rising
                }
                _ => false,
            };
            l.last_x = Some(xi);
            if pulse {
                out.pulse_at(t);
            }
        }
        // data recorder
        if let Some(s) = self.wave.rec_start {
            let rtr = u64::from(self.wave.rtr.max(1));
            if k >= s && (k - s).is_multiple_of(rtr) {
                let cap = self.wave.cfg.record_points;
                let mut full = true;
                for r in &mut self.wave.rec {
                    if r.option == 0 {
                        continue;
                    }
                    if r.data.len() < cap {
                        full = false;
                        r.data.push(match r.option {
                            1 => tgt[r.axis],
                            2 => x[r.axis],
                            _ => tgt[r.axis] - x[r.axis],
                        });
                    }
                }
                if full {
                    self.wave.rec_start = None;
                }
            }
        }
    }

    /// The wave generator, recorder and trigger-output commands; `None` if `cmd` is not one
    /// of them. The inner `Option` is the reply.
    pub(super) fn wave_command(&mut self, cmd: &str, args: &[&str]) -> Option<Option<String>> {
        let r = match cmd {
            "#9" => Ok(Some(format!(
                "{:X}",
                (0..3)
                    .filter(|&i| self.wave.gens[i].running)
                    .fold(0u32, |m, i| m | (1 << i))
            ))),
            "WAV" => self.wav(args).map(|_| None),
            "WAV?" => self.wav_q(args).map(Some),
            "WSL" | "WGC" | "WGO" => self.gen_pairs(cmd, args).map(|_| None),
            "WSL?" | "WGC?" | "WGO?" | "WTR?" => self.gen_query(cmd, args).map(Some),
            "WTR" => self.wtr(args).map(|_| None),
            "CTO" => self.cto(args).map(|_| None),
            "CTO?" => self.cto_q(args).map(Some),
            "TWS" => self.tws(args).map(|_| None),
            "TWC" => {
                for l in &mut self.wave.lines {
                    l.tws.clear();
                }
                Ok(None)
            }
            "DRC" => self.drc(args).map(|_| None),
            "DRC?" => self.rec_query(args, |w, axes, t| {
                let r = &w.rec[t];
                format!("{} {}", axes[r.axis], r.option)
            }),
            "DRL?" => self.rec_query(args, |w, _, t| w.rec[t].data.len().to_string()),
            "DRT" => self.drt(args).map(|_| None),
            "DRT?" => self.rec_query(args, |w, _, _| format!("{} 0", w.drt)),
            "RTR" => match args {
                [v] => match parse_u(v) {
                    Some(n) if n >= 1 && n <= u64::from(u32::MAX) => {
                        self.wave.rtr = n as u32;
                        Ok(None)
                    }
                    Some(_) => Err(17),
                    None => Err(1),
                },
                _ => Err(1),
            },
            "RTR?" if args.is_empty() => Ok(Some(self.wave.rtr.to_string())),
            "DRR?" => self.drr(args).map(Some),
            "SPA?" => self.spa_q(args).map(Some),
            "SPA" => self.spa(args).map(|_| None),
            "WMS?" => {
                let ids: Result<Vec<usize>, i64> = if args.is_empty() {
                    Ok((1..=self.wave.tables.len()).collect())
                } else {
                    args.iter().map(|a| self.table_id(a)).collect()
                };
                ids.map(|ids| {
                    Some(
                        ids.iter()
                            .map(|t| format!("{t}={}", self.wave.cfg.table_points))
                            .collect::<Vec<_>>()
                            .join(" \n"),
                    )
                })
            }
            _ => return None,
        };
        Some(match r {
            Ok(reply) => reply,
            Err(code) => {
                self.set_error(code);
                None
            }
        })
    }

    /// A query per record table (`DRC?`, `DRL?`, `DRT?`): lines `table=value`.
    fn rec_query(
        &mut self,
        args: &[&str],
        f: impl Fn(&Wave, &[String; 3], usize) -> String,
    ) -> Result<Option<String>, i64> {
        let ids: Vec<usize> = if args.is_empty() {
            (1..=self.wave.rec.len()).collect()
        } else {
            let mut v = Vec::new();
            for a in args {
                match parse_u(a) {
                    Some(t) if t >= 1 && (t as usize) <= self.wave.rec.len() => v.push(t as usize),
                    Some(_) => return Err(57),
                    None => return Err(1),
                }
            }
            v
        };
        let lines: Vec<String> = ids
            .iter()
            .map(|&t| format!("{t}={}", f(&self.wave, &self.cfg.axes, t - 1)))
            .collect();
        Ok(Some(lines.join(" \n")))
    }

    /// The parameter id of an `SPA`/`SPA?` item (decimal or `0x` hex) on one of the emulated
    /// axes: error 15 for an unknown axis, 1 for an id that is not a number.
    fn axis_param(&self, axis: &str, id: &str) -> Result<u32, i64> {
        if !self.cfg.axes.iter().any(|a| a == axis) {
            return Err(15);
        }
        match id.strip_prefix("0x").or_else(|| id.strip_prefix("0X")) {
            Some(h) => u32::from_str_radix(h, 16).ok(),
            None => id.parse::<u32>().ok(),
        }
        .ok_or(1)
    }

    /// `SPA? {<item> <parameter id>}`: the wave generator's and recorder's parameters
    /// (E-727 parameter list; PIPython's `getservotime`/`getmaxnumvalues` read the same ids):
    /// 0x0E000200 Servo Update Time (s), 0x16000200 Data Recorder Max Points (all tables
    /// together), 0x16000300 Data Recorder Chan Number (tables). Lines `item id=value`, the id
    /// as given. Error 15 for an unknown item, 54 for a parameter not emulated.
    fn spa_q(&mut self, args: &[&str]) -> Result<String, i64> {
        let mut out = Vec::new();
        for c in groups::<2>(args)? {
            let id = self.axis_param(c[0], c[1])?;
            let v = match id {
                0x0E00_0200 => format!("{:e}", self.wave.cfg.servo_cycle_s),
                0x1600_0200 => {
                    (self.wave.cfg.record_points * self.wave.cfg.record_tables).to_string()
                }
                0x1600_0300 => self.wave.cfg.record_tables.to_string(),
                0x0700_0900 => format!("{:.6}", self.window_um[axis_index(&self.cfg.axes, c[0])]),
                0x0700_0901 => format!("{:.6}", self.settling_s[axis_index(&self.cfg.axes, c[0])]),
                _ => return Err(54),
            };
            out.push(format!("{} {}={v}", c[0], c[1]));
        }
        Ok(out.join(" \n"))
    }

    /// `SPA {<item> <parameter id> <value>}`: the settling window (0x07000900, µm) and the
    /// settling time (0x07000901, s) of an axis, which decide `ONT?` (E-727 manual). Error 15
    /// for an unknown axis, 54 for a parameter not emulated, 17 for a negative or non-finite
    /// value; nothing is changed unless every triple is valid.
    fn spa(&mut self, args: &[&str]) -> Result<(), i64> {
        let mut set = Vec::new();
        for c in groups::<3>(args)? {
            let id = self.axis_param(c[0], c[1])?;
            let v: f64 = c[2].parse().map_err(|_| 1i64)?;
            if !(v.is_finite() && v >= 0.0) {
                return Err(17);
            }
            if !matches!(id, 0x0700_0900 | 0x0700_0901) {
                return Err(54);
            }
            set.push((axis_index(&self.cfg.axes, c[0]), id, v));
        }
        for (i, id, v) in set {
            if id == 0x0700_0900 {
                self.window_um[i] = v;
            } else {
                self.settling_s[i] = v;
            }
        }
        Ok(())
    }

    fn gen_id(&self, s: &str) -> Result<usize, i64> {
        match parse_u(s) {
            Some(g) if (1..=3).contains(&g) => Ok(g as usize - 1),
            Some(_) => Err(17),
            None => Err(1),
        }
    }

    fn table_id(&self, s: &str) -> Result<usize, i64> {
        match parse_u(s) {
            Some(t) if t >= 1 && (t as usize) <= self.wave.tables.len() => Ok(t as usize),
            Some(_) => Err(17),
            None => Err(1),
        }
    }

    /// `WAV <table> <X|&|+> LIN <seglength> <amplitude> <offset> <numpoints> <firstpoint>
    /// <speedupdown>`, `… RAMP … <speedupdown> <center>`, `WAV <table> <X|&|+> PNT
    /// <firstpoint> <numpoints> <p1> …`.
    fn wav(&mut self, args: &[&str]) -> Result<(), i64> {
        if args.len() < 3 {
            return Err(1);
        }
        let t = self.table_id(args[0])?;
        if self.wave.gens.iter().any(|g| g.running && g.table == t) {
            return Err(73);
        }
        let append = args[1];
        let kind = args[2].to_ascii_uppercase();
        let nums = &args[3..];
        let f = |i: usize| nums.get(i).and_then(|s| parse_f(s)).ok_or(1i64);
        let u = |i: usize| nums.get(i).and_then(|s| parse_u(s)).ok_or(1i64);
        let segment: Vec<f64> = match kind.as_str() {
            "LIN" | "RAMP" => {
                let want = if kind == "LIN" { 6 } else { 7 };
                if nums.len() != want {
                    return Err(1);
                }
                let (seg, amp, off, n, first, s) = (
                    u(0)? as usize,
                    f(1)?,
                    f(2)?,
                    u(3)? as usize,
                    u(4)? as usize,
                    u(5)? as usize,
                );
                if seg == 0 || n == 0 || first + n > seg {
                    return Err(17);
                }
                let curve = if kind == "LIN" {
                    if 2 * s + 1 > n {
                        return Err(17);
                    }
                    lin_curve(amp, n, s)
                } else {
                    let c = u(6)? as usize;
                    if c == 0 || c + 1 >= n || 2 * s > c || 2 * s > n - 1 - c {
                        return Err(17);
                    }
                    let mut up = lin_curve(amp, c + 1, s);
                    let down = lin_curve(amp, n - c, s);
                    up.extend(down.iter().rev().skip(1));
                    up
                };
                let end = *curve.last().unwrap_or(&0.0);
                (0..seg)
                    .map(|i| {
                        off + if i < first {
                            0.0
                        } else if i < first + n {
                            curve[i - first]
                        } else if kind == "LIN" {
                            end
                        } else {
                            0.0
                        }
                    })
                    .collect()
            }
            "PNT" => {
                if nums.len() < 3 {
                    return Err(1);
                }
                let (first, n) = (u(0)? as usize, u(1)? as usize);
                if nums.len() != 2 + n || first < 1 {
                    return Err(if first < 1 { 17 } else { 1 });
                }
                let mut v = vec![0.0; first - 1];
                for i in 0..n {
                    v.push(f(2 + i)?);
                }
                v
            }
            _ => return Err(1),
        };
        let table = &mut self.wave.tables[t - 1];
        let new_len = match append {
            "X" | "x" => segment.len(),
            "&" => table.len() + segment.len(),
            "+" => table.len().max(segment.len()),
            _ => return Err(1),
        };
        if new_len > self.wave.cfg.table_points {
            return Err(67);
        }
        match append {
            "X" | "x" => *table = segment,
            "&" => table.extend(segment),
            _ => {
                table.resize(new_len, 0.0);
                for (a, b) in table.iter_mut().zip(segment) {
                    *a += b;
                }
            }
        }
        Ok(())
    }

    /// `WAV? <table> <param>` pairs; param 1 = the table's length in points.
    fn wav_q(&mut self, args: &[&str]) -> Result<String, i64> {
        let mut lines = Vec::new();
        for c in groups::<2>(args)? {
            let t = self.table_id(c[0])?;
            if parse_u(c[1]) != Some(1) {
                return Err(17);
            }
            lines.push(format!("{t} 1={}", self.wave.tables[t - 1].len()));
        }
        Ok(lines.join(" \n"))
    }

    fn gen_pairs(&mut self, cmd: &str, args: &[&str]) -> Result<(), i64> {
        let mut pairs = Vec::new();
        for c in groups::<2>(args)? {
            let g = self.gen_id(c[0])?;
            let v = parse_u(c[1]).ok_or(1i64)?;
            pairs.push((g, v));
        }
        // check everything before changing anything
        for &(g, v) in &pairs {
            match cmd {
                "WSL" => {
                    if self.wave.gens[g].running {
                        return Err(73);
                    }
                    if v as usize > self.wave.tables.len() {
                        return Err(17);
                    }
                }
                "WGC" => {
                    if v > u64::from(u32::MAX) {
                        return Err(17);
                    }
                }
                _ => {
                    // WGO: 0 stop; 1 start at once; 0x101 start at once, at the end point of
                    // the last cycle (same here: a single cycle ends there)
                    if v == 0 {
                        continue;
                    }
                    if v != 1 && v != 0x101 {
                        return Err(17);
                    }
                    let gen = &self.wave.gens[g];
                    if gen.table == 0 || self.wave.tables[gen.table - 1].is_empty() {
                        return Err(75);
                    }
                    if !self.axes[g].servo {
                        return Err(5);
                    }
                    let (lo, hi) = self.cfg.travel[g];
                    let reject = super::lock(&self.faults).reject_out_of_range;
                    if reject
                        && self.wave.tables[gen.table - 1]
                            .iter()
                            .any(|&p| p < lo.min(hi) || p > hi.max(lo))
                    {
                        return Err(7);
                    }
                }
            }
        }
        let now = Instant::now();
        let mut started = false;
        for (g, v) in pairs {
            match cmd {
                "WSL" => self.wave.gens[g].table = v as usize,
                "WGC" => self.wave.gens[g].cycles = v as u32,
                _ => {
                    self.wave.gens[g].mode = v as u32;
                    if v == 0 {
                        if self.wave.gens[g].running {
                            self.wave.truncate_path();
                        }
                        self.wave.gens[g].running = false;
                    } else {
                        let (p, _) = self.axis_now(g, now);
                        let a = &mut self.axes[g];
                        a.lag = Some(p);
                        a.tripped = false;
                        let gen = &mut self.wave.gens[g];
                        gen.running = true;
                        gen.start = self.wave.cycle + 1;
                        gen.point = 0;
                        started = true;
                    }
                }
            }
        }
        if started && (self.wave.drt == 0 || self.wave.drt == 1) {
            self.wave.trigger_recording();
        }
        if started {
            self.publish_path(now);
        }
        Ok(())
    }

    fn gen_query(&mut self, cmd: &str, args: &[&str]) -> Result<String, i64> {
        let ids: Vec<usize> = if args.is_empty() {
            vec![0, 1, 2]
        } else {
            args.iter()
                .map(|a| self.gen_id(a))
                .collect::<Result<_, _>>()?
        };
        Ok(ids
            .iter()
            .map(|&g| {
                let gen = &self.wave.gens[g];
                let v = match cmd {
                    "WSL?" => gen.table.to_string(),
                    "WGC?" => gen.cycles.to_string(),
                    "WGO?" => gen.mode.to_string(),
                    _ => format!("{} {}", gen.rate, gen.interp),
                };
                format!("{}={v}", g + 1)
            })
            .collect::<Vec<_>>()
            .join(" \n"))
    }

    /// `WTR <gen> <rate> <interpolation>` triplets; gen 0 = all generators.
    fn wtr(&mut self, args: &[&str]) -> Result<(), i64> {
        let mut set = Vec::new();
        for c in groups::<3>(args)? {
            let g = parse_u(c[0]).ok_or(1i64)?;
            let rate = parse_u(c[1]).ok_or(1i64)?;
            let interp = parse_u(c[2]).ok_or(1i64)?;
            if g > 3 || rate == 0 || rate > u64::from(u32::MAX) || interp > 1 {
                return Err(17);
            }
            let gens: Vec<usize> = if g == 0 {
                vec![0, 1, 2]
            } else {
                vec![g as usize - 1]
            };
            for i in gens {
                if self.wave.gens[i].running {
                    return Err(73);
                }
                set.push((i, rate as u32, interp as u32));
            }
        }
        for (i, rate, interp) in set {
            self.wave.gens[i].rate = rate;
            self.wave.gens[i].interp = interp;
        }
        Ok(())
    }

    fn line_id(s: &str) -> Result<usize, i64> {
        match parse_u(s) {
            Some(l) if (1..=3).contains(&l) => Ok(l as usize - 1),
            Some(_) => Err(17),
            None => Err(1),
        }
    }

    /// `CTO {<line> <param> <value>}`.
    fn cto(&mut self, args: &[&str]) -> Result<(), i64> {
        let mut lines = self.wave.lines.clone();
        for c in groups::<3>(args)? {
            let li = Self::line_id(c[0])?;
            let p = parse_u(c[1]).ok_or(1i64)?;
            let l = &mut lines[li];
            match p {
                2 => l.axis = self.cfg.axes.iter().position(|n| n == c[2]).ok_or(15i64)?,
                1 | 3 | 5..=9 => {
                    let v = parse_f(c[2]).ok_or(1i64)?;
                    match p {
                        1 if v >= 0.0 => l.step = v,
                        3 if [0.0, 2.0, 3.0, 4.0].contains(&v) => l.mode = Some(v as u32),
                        5 => l.min = v,
                        6 => l.max = v,
                        7 if v == 0.0 || v == 1.0 => l.polarity = v as u32,
                        8 => l.start = v,
                        9 => l.stop = v,
                        _ => return Err(17),
                    }
                }
                _ => return Err(17),
            }
            l.level = false;
            l.next = None;
            l.last_x = None;
        }
        for (dst, src) in self.wave.lines.iter_mut().zip(lines) {
            let tws = std::mem::take(&mut dst.tws);
            *dst = TrigLine { tws, ..src };
        }
        Ok(())
    }

    /// `CTO? [<line> <param> …]`: lines `line param=value`.
    fn cto_q(&mut self, args: &[&str]) -> Result<String, i64> {
        let pairs: Vec<(usize, u64)> = if args.is_empty() {
            (0..3)
                .flat_map(|l| [1, 2, 3, 5, 6, 7, 8, 9].map(|p| (l, p)))
                .collect()
        } else {
            let mut v = Vec::new();
            for c in groups::<2>(args)? {
                v.push((Self::line_id(c[0])?, parse_u(c[1]).ok_or(1i64)?));
            }
            v
        };
        let mut out = Vec::new();
        for (li, p) in pairs {
            let l = &self.wave.lines[li];
            let v = match p {
                1 => format!("{:.6}", l.step),
                2 => self.cfg.axes[l.axis].clone(),
                3 => l.mode.map_or("0".into(), |m| m.to_string()),
                5 => format!("{:.6}", l.min),
                6 => format!("{:.6}", l.max),
                7 => l.polarity.to_string(),
                8 => format!("{:.6}", l.start),
                9 => format!("{:.6}", l.stop),
                _ => return Err(17),
            };
            out.push(format!("{} {p}={v}", li + 1));
        }
        Ok(out.join(" \n"))
    }

    /// `TWS {<line> <point> <switch>}`: the level of a trigger line at a wave point.
    fn tws(&mut self, args: &[&str]) -> Result<(), i64> {
        let mut set = Vec::new();
        for c in groups::<3>(args)? {
            let li = Self::line_id(c[0])?;
            let point = parse_u(c[1]).ok_or(1i64)?;
            let sw = parse_u(c[2]).ok_or(1i64)?;
            if point < 1 || point as usize > self.wave.cfg.table_points || sw > 1 {
                return Err(17);
            }
            set.push((li, point as usize, sw == 1));
        }
        for (li, p, v) in set {
            self.wave.lines[li].tws.insert(p, v);
        }
        Ok(())
    }

    /// `DRC {<table> <source> <option>}`.
    fn drc(&mut self, args: &[&str]) -> Result<(), i64> {
        let mut set = Vec::new();
        for c in groups::<3>(args)? {
            let t = match parse_u(c[0]) {
                Some(t) if t >= 1 && (t as usize) <= self.wave.rec.len() => t as usize - 1,
                Some(_) => return Err(57),
                None => return Err(1),
            };
            let axis = self.cfg.axes.iter().position(|n| n == c[1]).ok_or(59i64)?;
            let opt = match parse_u(c[2]) {
                Some(o) if o <= 3 => o as u32,
                Some(_) => return Err(58),
                None => return Err(1),
            };
            set.push((t, axis, opt));
        }
        for (t, axis, option) in set {
            // a new configuration resets the table's point count (C-863 manual, DRL?)
            self.wave.rec[t] = Rec {
                axis,
                option,
                data: Vec::new(),
            };
        }
        Ok(())
    }

    /// `DRT <table> <source> <value>`; table 0 = all (one trigger for the whole recorder).
    fn drt(&mut self, args: &[&str]) -> Result<(), i64> {
        let [t, s, _v] = args else {
            return Err(1);
        };
        let t = parse_u(t).ok_or(1i64)?;
        if t as usize > self.wave.rec.len() {
            return Err(57);
        }
        match parse_u(s) {
            Some(src @ (0 | 1)) => self.wave.drt = src as u32,
            Some(4) => {
                self.wave.drt = 4;
                self.wave.trigger_recording();
            }
            Some(_) => return Err(17),
            None => return Err(1),
        }
        Ok(())
    }

    /// `DRR? [<start> <n> [<table> …]]`: the GCS array.
    fn drr(&mut self, args: &[&str]) -> Result<String, i64> {
        let (start, n, tables): (usize, Option<usize>, Vec<usize>) = match args {
            [] => (1, None, Vec::new()),
            [_] => return Err(1),
            [s, n, rest @ ..] => {
                let s = parse_u(s).ok_or(1i64)? as usize;
                let n = parse_u(n).ok_or(1i64)? as usize;
                if s < 1 || n < 1 {
                    return Err(17);
                }
                let mut v = Vec::new();
                for t in rest {
                    match parse_u(t) {
                        Some(t) if t >= 1 && (t as usize) <= self.wave.rec.len() => {
                            v.push(t as usize - 1)
                        }
                        Some(_) => return Err(57),
                        None => return Err(1),
                    }
                }
                (s, Some(n), v)
            }
        };
        let tables: Vec<usize> = if tables.is_empty() {
            (0..self.wave.rec.len())
                .filter(|&t| self.wave.rec[t].option != 0)
                .collect()
        } else {
            tables
        };
        if tables.is_empty() {
            return Err(57);
        }
        let have = tables
            .iter()
            .map(|&t| self.wave.rec[t].data.len())
            .min()
            .unwrap_or(0);
        let n = n.unwrap_or(have.saturating_sub(start - 1));
        if start - 1 + n > have || n == 0 {
            return Err(77);
        }
        let sample = self.wave.dt() * f64::from(self.wave.rtr.max(1));
        let mut out = String::new();
        let mut head = |k: &str, v: String| out.push_str(&format!("# {k} = {v} \n"));
        head("VERSION", "1".into());
        head("TYPE", "1".into());
        head("SEPARATOR", "32".into());
        head("DIM", tables.len().to_string());
        head("SAMPLE_TIME", format!("{sample:.9}"));
        head("NDATA", n.to_string());
        for (c, &t) in tables.iter().enumerate() {
            let r = &self.wave.rec[t];
            let what = match r.option {
                1 => "Target Position",
                2 => "Current Position",
                _ => "Position Error",
            };
            head(
                &format!("NAME{c}"),
                format!("{what} of axis {}", self.cfg.axes[r.axis]),
            );
        }
        out.push_str("# END_HEADER \n");
        for i in 0..n {
            let row: Vec<String> = tables
                .iter()
                .map(|&t| format!("{:.6}", self.wave.rec[t].data[start - 1 + i]))
                .collect();
            out.push_str(&row.join(" "));
            out.push_str(if i + 1 < n { " \n" } else { "" });
        }
        Ok(out)
    }
}

/// The index of axis identifier `id` among `axes` (0 when absent: callers check first).
fn axis_index(axes: &[String; 3], id: &str) -> usize {
    axes.iter().position(|a| a == id).unwrap_or(0)
}
