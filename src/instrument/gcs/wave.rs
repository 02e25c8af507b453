//! Hardware-timed line sweeps on a PI GCS 2.0 controller: the wave generator drives one axis
//! along a constant-speed line under the controller's servo clock, a digital output pulses at
//! the first wave point (to start a digitiser), and the data recorder keeps the target and
//! the measured position of every servo sample.
//!
//! Commands (PI GCS 2.0; argument order as PIPython's `gcsbasecommands.py` documents it):
//!
//! | command | use |
//! |---|---|
//! | `WAV t X LIN seg amp off n 0 s` | the line: `n` points from `off` to `off + amp` (µm), `s` points of speed-up/down at each end |
//! | `WSL g t`, `WGC g 1`, `WTR g r 0` | generator `g` (the axis' position in `SAI?`) plays table `t` once, `r` servo cycles per point; a snake raster keeps its forward and back waves in two tables and switches with `WSL` alone |
//! | `CTO l 2 axis l 3 4`, `TWC`, `TWS l 1 1 l 2 0` | output `l` in generator-trigger mode: high at wave point 1 only, one pulse per line |
//! | `DRC 1 axis 1 2 axis 2`, `RTR r` | record tables 1, 2: target and current position every `r` cycles |
//! | `WGO g 1` | start (the recorder triggers on it, `DRT` default) |
//! | `#9` (or `WGO?`) | poll until the generator has stopped |
//! | `DRL? 1 2`, `DRR? 1 N 1 2` | wait for the points, read them as a GCS array |
//! | `WGO g 0`, `STP` | on abort and after any fault |
//!
//! Units: positions in µm at this interface (`units_per_um` converts), times in s. The
//! driver only configures, starts, reads and stops: the sweep's limits and speed are checked
//! by `acquire/` before anything moves.

pub use super::super::line::{LineSweep, LineTiming, SweepRecord};
use super::{DeviceError, GcsStage};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// A GCS array (`DRR?` and friends): header `KEY = VALUE` pairs and the data columns.
#[derive(Debug, Clone, PartialEq)]
pub struct GcsArray {
    pub header: Vec<(String, String)>,
    pub columns: Vec<Vec<f64>>,
}

impl GcsArray {
    pub fn get(&self, key: &str) -> Option<&str> {
        self.header
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }
}

/// Parse the lines of a GCS array reply (marker spaces removed): `# KEY = VALUE` header lines
/// up to `# END_HEADER`, then rows of `DIM` numbers separated by `SEPARATOR` (32, a space).
/// `Err` names what is wrong.
pub fn parse_gcs_array(lines: &[String]) -> Result<GcsArray, String> {
    let mut header = Vec::new();
    let mut it = lines.iter();
    let mut ended = false;
    for l in it.by_ref() {
        let Some(h) = l.strip_prefix('#') else {
            return Err(format!("header line without `#`: {l:?}"));
        };
        let h = h.trim();
        if h.eq_ignore_ascii_case("END_HEADER") {
            ended = true;
            break;
        }
        if let Some((k, v)) = h.split_once('=') {
            header.push((k.trim().to_string(), v.trim().to_string()));
        }
    }
    if !ended {
        return Err("no `# END_HEADER` line".into());
    }
    let num = |k: &str| -> Result<usize, String> {
        header
            .iter()
            .find(|(h, _)| h == k)
            .and_then(|(_, v)| v.parse::<usize>().ok())
            .ok_or_else(|| format!("no numeric {k} in the header"))
    };
    let dim = num("DIM")?;
    let ndata = num("NDATA")?;
    let sep = num("SEPARATOR").unwrap_or(32);
    let sep = char::from_u32(sep as u32).unwrap_or(' ');
    let mut columns = vec![Vec::with_capacity(ndata); dim];
    for (i, l) in it.enumerate() {
        let vals: Vec<f64> = l
            .split(sep)
            .filter(|s| !s.trim().is_empty())
            .map(|s| s.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| format!("row {} is not numbers: {l:?}", i + 1))?;
        if vals.len() != dim {
            return Err(format!(
                "row {} has {} values, DIM is {dim}: {l:?}",
                i + 1,
                vals.len()
            ));
        }
        for (c, v) in columns.iter_mut().zip(vals) {
            c.push(v);
        }
    }
    let rows = columns.first().map_or(0, Vec::len);
    if rows != ndata {
        return Err(format!("{rows} rows, NDATA is {ndata}"));
    }
    Ok(GcsArray { header, columns })
}

/// What the controller holds for hardware-timed lines, as this driver set it: the waves in
/// its tables, the table selected and the generator, trigger and recorder settings.
#[derive(Debug, Clone, Default)]
pub struct WaveCache {
    /// (table, the `WAV` arguments after the table number).
    tables: Vec<(u32, String)>,
    /// The table `WSL` selected last.
    selected: Option<u32>,
    /// The settings of the last full configuration (generator, axis, rates, trigger line).
    setup: Option<String>,
}

/// Most rows a GCS array reply may have.
const MAX_ARRAY_ROWS: usize = 1 << 20;

impl GcsStage {
    /// The controller identifier and wave generator (its 1-based position in `SAI?`) of stage
    /// axis `axis`.
    fn generator_of(&self, axis: usize) -> Result<(String, usize), DeviceError> {
        let id = self
            .axes
            .iter()
            .find(|(i, _)| *i == axis)
            .map(|(_, a)| a.clone())
            .ok_or_else(|| DeviceError::Other {
                device: self.link.device().to_string(),
                detail: format!(
                    "axis {} is not driven by this controller",
                    ["x", "y", "z"].get(axis).unwrap_or(&"?")
                ),
            })?;
        let g = self.sai.iter().position(|s| *s == id).map_or(1, |p| p + 1);
        Ok((id, g))
    }

    fn other(&self, detail: String) -> DeviceError {
        DeviceError::Other {
            device: self.link.device().to_string(),
            detail,
        }
    }

    /// Configure the wave, the generator, the trigger output and the recorder for `s`
    /// (nothing moves).
    ///
    /// Two wave tables are kept loaded, `s.table` and `s.table + 1`: a snake raster's forward
    /// and back waves. A wave already in a table is not sent again, and when the generator,
    /// trigger and recorder settings are those already set, the line costs one `WSL g t`
    /// (select the table) instead of the nine commands of a full configuration. A new wave
    /// goes into the table not selected now. Any error forgets what is loaded (the next line
    /// configures everything again).
    pub fn wave_configure(&mut self, s: &LineSweep) -> Result<(), DeviceError> {
        if !(s.from_um.is_finite() && s.to_um.is_finite())
            || s.points < 2
            || 2 * s.speedupdown + 1 > s.points
            || s.rate == 0
            || s.record_rate == 0
            || !(s.servo_cycle_s.is_finite() && s.servo_cycle_s > 0.0)
            || s.table == 0
            || s.table == u32::MAX
        {
            return Err(self.other(format!("refusing to configure the line sweep {s:?}")));
        }
        let r = self.wave_configure_cached(s);
        if r.is_err() {
            self.waves = WaveCache::default();
        }
        r
    }

    fn wave_configure_cached(&mut self, s: &LineSweep) -> Result<(), DeviceError> {
        let (id, g) = self.generator_of(s.axis)?;
        let u = self.opts.units_per_um;
        // the wave, without its table number
        let wave = format!(
            "X LIN {n} {amp:.6} {off:.6} {n} 0 {sud}",
            n = s.points,
            amp = (s.to_um - s.from_um) * u,
            off = s.from_um * u,
            sud = s.speedupdown
        );
        let tables = [s.table, s.table + 1];
        let loaded = self
            .waves
            .tables
            .iter()
            .find(|(t, w)| tables.contains(t) && *w == wave)
            .map(|(t, _)| *t);
        let t = match loaded {
            Some(t) => t,
            None => {
                // the table of the pair not selected now (the first when none is)
                let t = if self.waves.selected == Some(tables[0]) {
                    tables[1]
                } else {
                    tables[0]
                };
                self.waves.tables.retain(|(k, _)| *k != t);
                self.command(&format!("WAV {t} {wave}"))?;
                self.waves.tables.push((t, wave));
                t
            }
        };
        let setup = format!(
            "{g} {id} {} {} {:?} {}",
            s.rate, s.record_rate, s.trigger_line, tables[0]
        );
        if self.waves.setup.as_deref() == Some(setup.as_str()) {
            if self.waves.selected != Some(t) {
                self.waves.selected = None;
                self.command(&format!("WSL {g} {t}"))?;
                self.waves.selected = Some(t);
            }
            return Ok(());
        }
        self.waves.setup = None;
        self.waves.selected = None;
        self.command(&format!("WSL {g} {t}"))?;
        self.waves.selected = Some(t);
        self.command(&format!("WGC {g} 1"))?;
        self.command(&format!("WTR {g} {} 0", s.rate))?;
        if let Some(l) = s.trigger_line {
            self.command(&format!("CTO {l} 2 {id} {l} 3 4"))?;
            self.command("TWC")?;
            self.command(&format!("TWS {l} 1 1 {l} 2 0"))?;
        }
        self.command(&format!("DRC 1 {id} 1 2 {id} 2"))?;
        self.command(&format!("RTR {}", s.record_rate))?;
        self.waves.setup = Some(setup);
        Ok(())
    }

    /// Forget the wave tables loaded and the generator settings: the next line configures
    /// everything again (as every line did before two tables were kept; used to measure the
    /// difference, docs/performance.md).
    pub fn forget_waves(&mut self) {
        self.waves = WaveCache::default();
    }

    /// `WGO g 1`: start the line (the recorder starts with it).
    pub fn wave_start(&mut self, s: &LineSweep) -> Result<(), DeviceError> {
        let (_, g) = self.generator_of(s.axis)?;
        // the target changes under the generator: read it again after the line
        self.commanded = None;
        self.command(&format!("WGO {g} 1"))
    }

    /// Whether generator `g` runs: `#9` (bit g−1 of a hexadecimal mask).
    fn generator_running(&mut self, g: usize) -> Result<bool, DeviceError> {
        self.link.discard_input();
        self.link.send_raw(&[0x09], "#9")?;
        let line = self.link.read_line("#9", self.opts.timeout)?;
        let mask = u32::from_str_radix(line.trim(), 16)
            .map_err(|_| self.link.garbled("#9", line.clone()))?;
        Ok(mask & (1 << (g - 1)) != 0)
    }

    /// Poll `#9` until the line's generator has stopped. `Ok(false)`: `abort` was set (the
    /// generator and the axes are stopped). A generator still running at twice the line's
    /// duration plus the on-target timeout is a fault.
    pub fn wave_wait(&mut self, s: &LineSweep, abort: &AtomicBool) -> Result<bool, DeviceError> {
        let (_, g) = self.generator_of(s.axis)?;
        let limit = Duration::from_secs_f64(2.0 * s.duration_s()) + self.opts.on_target_timeout;
        let t0 = Instant::now();
        loop {
            if abort.load(Ordering::SeqCst) {
                self.wave_stop(s)?;
                return Ok(false);
            }
            if !self.generator_running(g)? {
                return Ok(true);
            }
            if t0.elapsed() > limit {
                return Err(self.other(format!(
                    "wave generator {g} still running {:.3} s after `WGO {g} 1` (the line takes {:.3} s)",
                    t0.elapsed().as_secs_f64(),
                    s.duration_s()
                )));
            }
            std::thread::sleep(self.opts.poll_interval);
        }
    }

    /// Read `n` samples of record tables 1 and 2: wait until `DRL?` has them, then `DRR? 1 n
    /// 1 2`.
    pub fn read_record(&mut self, n: usize) -> Result<SweepRecord, DeviceError> {
        let t0 = Instant::now();
        loop {
            let lines = self.query_lines("DRL? 1 2")?;
            let have = lines
                .iter()
                .map(|l| {
                    l.split_once('=')
                        .and_then(|(_, v)| v.trim().parse::<usize>().ok())
                })
                .collect::<Option<Vec<usize>>>()
                .filter(|v| v.len() == 2)
                .ok_or_else(|| self.link.garbled("DRL? 1 2", lines.join("\\n")))?;
            if have.iter().all(|&h| h >= n) {
                break;
            }
            if t0.elapsed() > self.opts.on_target_timeout {
                return Err(self.other(format!(
                    "the data recorder holds {have:?} points after {:.3} s, {n} expected (`DRL? 1 2`)",
                    t0.elapsed().as_secs_f64()
                )));
            }
            std::thread::sleep(self.opts.poll_interval);
        }
        let cmd = format!("DRR? 1 {n} 1 2");
        // the reply is long (about 24 bytes a row, a 300-byte header): on a serial link its
        // wire time (50 kB: 4.3 s at 115200 baud) comes on top of the reply timeout
        let wire = self
            .wire_bytes_per_s
            .map_or(0.0, |b| (300.0 + 24.0 * n as f64) / b);
        let timeout = self.opts.timeout + Duration::from_secs_f64(1.5 * wire);
        let a = self.query_gcs_array_within(&cmd, timeout)?;
        let u = self.opts.units_per_um;
        let bad = |why: String| self.link.garbled(&cmd, why);
        if a.columns.len() != 2 || a.columns[0].len() != n {
            return Err(bad(format!(
                "{} columns of {} rows, 2 of {n} asked",
                a.columns.len(),
                a.columns.first().map_or(0, Vec::len)
            )));
        }
        let sample_time_s = a
            .get("SAMPLE_TIME")
            .and_then(|v| v.parse::<f64>().ok())
            .filter(|v| v.is_finite() && *v > 0.0)
            .ok_or_else(|| bad("no positive SAMPLE_TIME in the header".into()))?;
        let mut cols = a.columns.into_iter();
        let conv = |v: Vec<f64>| v.into_iter().map(|x| x / u).collect::<Vec<_>>();
        let target_um = conv(cols.next().unwrap_or_default());
        let position_um = conv(cols.next().unwrap_or_default());
        Ok(SweepRecord {
            sample_time_s,
            target_um,
            position_um,
        })
    }

    /// Send a query answered by a GCS array and parse it. A rejected query (no reply) is the
    /// controller's error; a malformed array is `Garbled` with what came.
    pub fn query_gcs_array(&mut self, cmd: &str) -> Result<GcsArray, DeviceError> {
        self.query_gcs_array_within(cmd, self.opts.timeout)
    }

    /// As [`query_gcs_array`](Self::query_gcs_array), waiting at most `timeout` for each line.
    fn query_gcs_array_within(
        &mut self,
        cmd: &str,
        timeout: Duration,
    ) -> Result<GcsArray, DeviceError> {
        // more than MAX_ARRAY_ROWS lines is too many
        let lines = self.query_lines_within(cmd, timeout, MAX_ARRAY_ROWS + 1, |_| {
            format!("more than {MAX_ARRAY_ROWS} lines")
        })?;
        let a = parse_gcs_array(&lines).map_err(|why| {
            let head: Vec<&str> = lines.iter().take(12).map(String::as_str).collect();
            self.link
                .garbled(cmd, format!("{why}; reply began {:?}", head.join("\\n")))
        })?;
        match self.error_code(cmd)? {
            0 => Ok(a),
            code => Err(self.controller_error(cmd, code)),
        }
    }

    /// `WGO g 0` then `STP`: the generator off, every axis stopped. Both are sent even if the
    /// first fails; the first error is returned.
    pub fn wave_stop(&mut self, s: &LineSweep) -> Result<(), DeviceError> {
        // a fault may have left the rest of a long reply (a `DRR?` that timed out) on the
        // line: let it pass, so that `STP`'s `ERR?` reads its own answer
        self.drain_until_quiet(Duration::from_millis(20), Duration::from_secs(10));
        let r1 = self
            .generator_of(s.axis)
            .and_then(|(_, g)| self.link.send(&format!("WGO {g} 0")));
        let r2 = self.send_stop();
        r1.and(r2)
    }

    /// Read and drop whatever arrives until the link has been quiet for `quiet` (at most
    /// `limit` in all).
    fn drain_until_quiet(&mut self, quiet: Duration, limit: Duration) {
        let t0 = Instant::now();
        while t0.elapsed() < limit {
            if self.link.read_line("(draining)", quiet).is_err() {
                break;
            }
        }
        self.link.discard_input();
    }

    /// `SPA? <item> <id>`: one parameter's value (the text after `=`).
    fn parameter(&mut self, item: &str, id: u32) -> Result<(String, String), DeviceError> {
        let cmd = format!("SPA? {item} 0x{id:08X}");
        let lines = self.query_lines(&cmd)?;
        let v = lines
            .first()
            .and_then(|l| l.split_once('='))
            .map(|(_, v)| v.trim().to_string())
            .ok_or_else(|| self.link.garbled(&cmd, lines.join("\\n")))?;
        Ok((cmd, v))
    }

    /// What the wave generator and the data recorder of this controller can do, read once
    /// per connection (PIPython's `getservotime` and `getmaxnumvalues` ask the same):
    /// - servo cycle: `SPA? <axis> 0x0E000200` (Servo Update Time, s);
    /// - points per wave table: `WMS? 1` (`1=<points>`);
    /// - points per record table: `SPA? <axis> 0x16000200` (Data Recorder Max Points, shared
    ///   by all tables) / `SPA? <axis> 0x16000300` (Data Recorder Chan Number).
    ///
    /// A query the controller rejects (a `Controller` error: an unknown command or
    /// parameter) falls back on the config value (`[stage] servo_cycle_s`, `max_wave_points`,
    /// `max_record_points`); with none configured the error says which key to set. A reply
    /// that is not a positive number is `Garbled`. `trigger_line` is the config's.
    pub fn read_line_timing(&mut self) -> Result<LineTiming, DeviceError> {
        if let Some(t) = self.line_timing {
            return Ok(t);
        }
        let item = self
            .axes
            .first()
            .map(|(_, a)| a.clone())
            .unwrap_or_else(|| "1".into());
        let fallback = |me: &Self, e: DeviceError, v: Option<f64>, key: &str| match (e, v) {
            (DeviceError::Controller { .. }, Some(v)) => Ok(v),
            (e @ DeviceError::Controller { .. }, None) => Err(me.other(format!(
                "{e}; set `[stage] {key}` in the config for a controller without it"
            ))),
            (e, _) => Err(e),
        };
        let positive = |me: &Self, cmd: &str, v: &str| {
            v.parse::<f64>()
                .ok()
                .filter(|x| x.is_finite() && *x > 0.0)
                .ok_or_else(|| me.link.garbled(cmd, v.to_string()))
        };
        let servo_cycle_s = match self.parameter(&item, 0x0E00_0200) {
            Ok((cmd, v)) => positive(self, &cmd, &v)?,
            Err(e) => fallback(self, e, self.opts.servo_cycle_s, "servo_cycle_s")?,
        };
        let max_wave_points = match self.query_lines("WMS? 1") {
            Ok(lines) => {
                let v = lines
                    .first()
                    .and_then(|l| l.split_once('='))
                    .map_or(String::new(), |(_, v)| v.trim().to_string());
                positive(self, "WMS? 1", &v)? as usize
            }
            Err(e) => fallback(
                self,
                e,
                self.opts.max_wave_points.map(|v| v as f64),
                "max_wave_points",
            )? as usize,
        };
        let max_record_points = match self
            .parameter(&item, 0x1600_0200)
            .and_then(|a| Ok((a, self.parameter(&item, 0x1600_0300)?)))
        {
            Ok(((c1, total), (c2, tables))) => {
                let total = positive(self, &c1, &total)?;
                let tables = positive(self, &c2, &tables)?;
                (total / tables).floor() as usize
            }
            Err(e) => fallback(
                self,
                e,
                self.opts.max_record_points.map(|v| v as f64),
                "max_record_points",
            )? as usize,
        };
        let t = LineTiming {
            servo_cycle_s,
            max_wave_points,
            max_record_points,
            trigger_line: self.opts.trigger_line,
        };
        self.line_timing = Some(t);
        Ok(t)
    }

    /// A whole line: configure, start, wait, read. Any fault (or `abort`) sends `WGO g 0` and
    /// `STP` before the error is returned; `Ok(None)` when aborted.
    pub fn sweep_line(
        &mut self,
        s: &LineSweep,
        abort: &AtomicBool,
    ) -> Result<Option<SweepRecord>, DeviceError> {
        let r = self.sweep_line_steps(s, abort);
        if r.is_err() {
            // best effort: the original fault is the one reported
            let _ = self.wave_stop(s);
        }
        r
    }

    fn sweep_line_steps(
        &mut self,
        s: &LineSweep,
        abort: &AtomicBool,
    ) -> Result<Option<SweepRecord>, DeviceError> {
        self.wave_configure(s)?;
        self.wave_start(s)?;
        if !self.wave_wait(s, abort)? {
            return Ok(None);
        }
        self.read_record(s.samples()).map(Some)
    }
}
