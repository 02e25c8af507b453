//! A raster frame streamed on one clock (`mode: "raster"` on a stage with a
//! [`FrameStream`]: an NI board whose outputs drive a Nano-Drive's external inputs and whose
//! inputs record the QPD and the fast axis's position monitor on the outputs' clock).
//!
//! - `prepare`: the lines of `raster::plan_lines` (each at constant speed `pitch / dwell` over
//!   its pixels plus a margin of `speed · settle_s` at each end, with speed ramps of
//!   `settle_s`), joined into one frame by turnarounds: both axes move from a line's end to
//!   the next line's start on a half-cosine of duration `max(settle_s, π/2 · distance /
//!   max_speed_um_s)` (at rest at both ends; its peak speed is `π/2 · distance / duration`).
//!   Every sample of the frame, converted to µm, is checked against the soft limits, the
//!   speed limit (between consecutive samples) and the outputs' range before anything moves.
//! - `step` (a line): the first step (and the first after a pause) starts the stream from
//!   where the stage stands, with a turnaround to the line's start; the outputs are written
//!   ahead of the clock in blocks (at most [`AHEAD_S`] ahead, and only what the outputs'
//!   buffer has room for: no write waits, so none holds up the reader), the inputs read in
//!   chunks of [`CHUNK_S`] ([`GUARD_CHUNK_S`] in the first [`GUARD_S`], where every sample of
//!   the measured position is compared with the plan: a stage that runs away is stopped); the line is binned by the measured position (`raster::bin_line`) as soon as
//!   its samples are in, and the stream goes on meanwhile. After the last line the outputs
//!   are held where the stage stands.
//! - `pause`, `stop`: the tasks stopped and cleared, the outputs held at the present position
//!   (never 0 V), the stage held at its reading (Madlib); a Ctrl-C takes effect after the line.
//!
//! Every device fault of the stream is the stage's (the outputs drive it): no further motion.
//! A line that cannot be binned is not.

use super::{
    line_by_line_steps, padded, planned, BinStats, Checked, Layout, StepFault, StepResult,
    StopCause, Strategy,
};
use crate::acquire::error::ScanError;
use crate::acquire::limits::SoftLimits;
use crate::acquire::plan::fmt_seconds;
use crate::acquire::raster::{bin_line, RasterOptions, RasterPlan};
use crate::instrument::line::LineTiming;
use crate::instrument::stream::{FrameStream, StreamChunk};
use crate::instrument::{DeviceError, Instrument, Pos, AXES};
use ndarray::Array2;
use serde_json::{json, Value};
use std::sync::Arc;
use std::time::Instant;

/// How far ahead of the clock the outputs are written, s.
pub const AHEAD_S: f64 = 0.5;
/// Inputs read at a time, s.
pub const CHUNK_S: f64 = 0.01;
/// After the last sample of the frame the outputs hold it for this long (s), so that the
/// generation never runs out of samples before the stream is stopped. Written like the
/// frame: only as much as the outputs' buffer takes, never ahead of the [`AHEAD_S`] budget.
pub const PAD_S: f64 = 0.5;
/// The stream's first this many seconds are read in [`GUARD_CHUNK_S`] chunks and each
/// sample of the sensor monitor compared with the plan (a stage that runs away is stopped
/// within a few ms).
pub const GUARD_S: f64 = 0.02;
/// Inputs read at a time while the guard watches, s: a quarter of a millisecond, so that the
/// first comparison comes that soon after the outputs start (a stage that runs away does so
/// with the stream's first sample).
pub const GUARD_CHUNK_S: f64 = 0.00025;
/// The guard's margin: a measured position farther than this outside the range of the
/// targets played so far is a stage that runs away, µm (a lagging stage stays inside it).
pub const GUARD_UM: f64 = 1.0;
/// A frame's speed ramps, margins and shortest turnarounds last this many of the stage's
/// measured lags (the time its measured position trails the target at constant speed): the
/// target runs two lags past the last pixel, so that the lagging stage crosses it at full
/// speed. Bins use the measured position, so nothing longer is needed.
pub const MARGIN_LAGS: f64 = 2.0;
/// Ramps and margins before any lag was measured (no move, no raster yet), s.
pub const DEFAULT_RAMP_S: f64 = 0.005;

/// The frame's ramp and margin time, s: [`MARGIN_LAGS`] × the stage's measured lag, or the
/// configured `settle_s` when that is longer; [`DEFAULT_RAMP_S`] before a lag was measured.
pub fn ramp_time(settle_s: f64, lag_s: Option<f64>) -> f64 {
    let lag = lag_s
        .filter(|l| l.is_finite() && *l >= 0.0)
        .map_or(DEFAULT_RAMP_S, |l| MARGIN_LAGS * l);
    settle_s.max(lag)
}

/// What set [`ramp_time`]: `"settle_s"`, `"measured lag"` or `"default"`.
fn ramp_source(settle_s: f64, lag_s: Option<f64>) -> &'static str {
    let t = ramp_time(settle_s, lag_s);
    if t == settle_s && settle_s > 0.0 {
        "settle_s"
    } else if lag_s.is_some() {
        "measured lag"
    } else {
        "default"
    }
}

/// Frames of at most this many samples keep their raw samples in the scan file.
pub const RAW_MAX_SAMPLES: usize = 2_000_000;

/// A piece of the frame's waveform.
#[derive(Debug, Clone, PartialEq)]
enum Seg {
    /// One sample at the present position (the frame's first).
    First([f64; 2]),
    /// A half-cosine from `a` to `b` (µm, fast and slow) over `n` samples: samples 1…n−1
    /// (sample 0 is the last of the piece before, sample n the first of the next).
    Turn { a: [f64; 2], b: [f64; 2], n: usize },
    /// Line `line` of the raster plan (its wave per sample), the slow axis at `slow`.
    Line { line: usize, slow: f64 },
}

/// The waveform of a frame from line `first` on, in samples of the outputs' clock.
#[derive(Debug, Clone)]
struct Frame {
    segs: Vec<(usize, Seg)>,
    /// (plan line, first sample, end sample) of each line in the frame.
    lines: Vec<(usize, usize, usize)>,
    len: usize,
    /// The last sample (µm), held after the frame.
    last: [f64; 2],
}

impl Frame {
    fn seg_len(s: &Seg, rp: &RasterPlan) -> usize {
        match s {
            Seg::First(_) => 1,
            Seg::Turn { n, .. } => n - 1,
            Seg::Line { line, .. } => {
                let w = &rp.lines[*line].sweep;
                w.points * w.rate.max(1) as usize
            }
        }
    }

    /// The frame from `at` (the present fast, slow position) through lines `first…`.
    fn new(rp: &RasterPlan, geo: &Geometry, first: usize, at: [f64; 2]) -> Frame {
        let mut segs = Vec::new();
        let mut lines = Vec::new();
        let mut len = 0;
        let push = |s: Seg, segs: &mut Vec<(usize, Seg)>, len: &mut usize| {
            let l = Self::seg_len(&s, rp);
            segs.push((*len, s));
            *len += l;
        };
        push(Seg::First(at), &mut segs, &mut len);
        let mut here = at;
        for (k, l) in rp.lines.iter().enumerate().skip(first) {
            let start = [l.sweep.from_um, l.start[geo.slow]];
            let n = geo.turn_samples(here, start);
            push(
                Seg::Turn {
                    a: here,
                    b: start,
                    n,
                },
                &mut segs,
                &mut len,
            );
            let s0 = len;
            push(
                Seg::Line {
                    line: k,
                    slow: start[1],
                },
                &mut segs,
                &mut len,
            );
            lines.push((k, s0, len));
            here = [l.sweep.to_um, start[1]];
        }
        Frame {
            segs,
            lines,
            len,
            last: here,
        }
    }

    /// Samples `from…from+n` (clipped to the frame) appended to `fast`, `slow`.
    fn fill(
        &self,
        rp: &RasterPlan,
        from: usize,
        n: usize,
        fast: &mut Vec<f64>,
        slow: &mut Vec<f64>,
    ) {
        let end = (from + n).min(self.len);
        let mut i = self.segs.partition_point(|(s0, _)| *s0 <= from).max(1) - 1;
        let mut k = from;
        while k < end {
            let (s0, seg) = &self.segs[i];
            let seg_end = self
                .segs
                .get(i + 1)
                .map_or(self.len, |(s1, _)| *s1)
                .min(end);
            match seg {
                Seg::First(p) => {
                    fast.push(p[0]);
                    slow.push(p[1]);
                }
                Seg::Turn { a, b, n } => {
                    for j in (k - s0 + 1)..(seg_end - s0 + 1) {
                        let u = 0.5 * (1.0 - (std::f64::consts::PI * j as f64 / *n as f64).cos());
                        fast.push(a[0] + (b[0] - a[0]) * u);
                        slow.push(a[1] + (b[1] - a[1]) * u);
                    }
                }
                Seg::Line { line, slow: y } => {
                    let w = &rp.lines[*line].sweep;
                    let r = w.rate.max(1) as usize;
                    for j in (k - s0)..(seg_end - s0) {
                        fast.push(w.wave_at(j / r));
                        slow.push(*y);
                    }
                }
            }
            k = seg_end;
            i += 1;
        }
    }
}

/// What the frame's turnarounds need: the rate, the settle time, the speed limit, the axes.
#[derive(Debug, Clone, Copy)]
struct Geometry {
    rate: f64,
    settle_s: f64,
    max_speed: Option<f64>,
    fast: usize,
    slow: usize,
}

impl Geometry {
    /// Samples of a turnaround from `a` to `b`: `max(settle_s, π/2 · |b − a| / max_speed)`
    /// at the rate, at least 4.
    fn turn_samples(&self, a: [f64; 2], b: [f64; 2]) -> usize {
        let d = (b[0] - a[0]).hypot(b[1] - a[1]);
        let t = match self.max_speed {
            Some(v) if v > 0.0 => self.settle_s.max(std::f64::consts::FRAC_PI_2 * d / v),
            _ => self.settle_s,
        };
        // sampled, the half-cosine's steps stay below its peak speed
        ((t * self.rate - 1e-9).ceil() as usize).max(4)
    }
}

/// The stream while it runs.
struct Running {
    frame: Frame,
    /// Samples written to the outputs (the frame, then its last sample held: `total`), read
    /// from the inputs.
    written: usize,
    total: usize,
    read: usize,
    /// The range of the fast axis's targets played so far (for the guard), µm.
    plan_lo: f64,
    plan_hi: f64,
    /// The range of the fast and slow axes' targets up to sample `now_upto` (for the guard's
    /// readings of the stage taken now, not on the clock), µm.
    now_lo: [f64; 2],
    now_hi: [f64; 2],
    now_upto: usize,
    /// Samples read and not yet binned, from sample `base` on.
    buf: StreamChunk,
    base: usize,
    /// The next line of `frame.lines` to bin.
    next: usize,
    t0: Instant,
}

/// Where the time went, s (summed over the scan).
#[derive(Default, Debug, Clone)]
struct Phases {
    lines: usize,
    starts: usize,
    start_s: f64,
    write_s: f64,
    writes: usize,
    /// The longest single write, s (the reader waits that long).
    max_write_s: f64,
    read_s: f64,
    reads: usize,
    convert_s: f64,
    bin_s: f64,
    hold_s: f64,
    /// The most samples the inputs were behind the clock when a read returned (an estimate
    /// from the stream's start time: the buffer holds `buffer_samples`).
    max_behind: usize,
    buffer_samples: usize,
    frame_samples: usize,
    stream_s: f64,
}

/// The frame stream. See the module documentation.
pub struct StreamStrategy {
    opts: RasterOptions,
    dwell_s: f64,
    rp: Option<Arc<RasterPlan>>,
    geo: Option<Geometry>,
    run: Option<Running>,
    stats: BinStats,
    ph: Phases,
    keep_raw: bool,
    raw: [Vec<Vec<f64>>; 5],
    at: Option<Pos>,
    /// The position the scan's other axes keep (the plan's base), µm.
    base: Pos,
    /// Samples of the centred moving average of the measured position (odd).
    smooth: usize,
    /// The stream was stopped at a pause.
    held: bool,
    /// Something was started (a stop is owed at the end of an interrupted scan).
    started: bool,
    /// The last line's pixels with samples at the rail, until the engine takes them.
    clipped: Vec<crate::acquire::clip::ClippedPixel>,
    /// The frame's ramp and margin time (s) and what set it ([`ramp_time`]).
    ramp: (f64, &'static str),
}

/// The stage's frame stream, or an error naming the stage.
fn stream_of(inst: &mut Instrument) -> Result<&mut dyn FrameStream, DeviceError> {
    let name = inst.stage.name();
    inst.stage.frame_stream().ok_or(DeviceError::Other {
        device: name,
        detail: "this stage has no frame stream".into(),
    })
}

impl StreamStrategy {
    pub fn new(opts: RasterOptions) -> StreamStrategy {
        StreamStrategy {
            opts,
            dwell_s: 0.0,
            rp: None,
            geo: None,
            run: None,
            stats: BinStats::default(),
            ph: Phases::default(),
            keep_raw: false,
            raw: Default::default(),
            at: None,
            base: [0.0; 3],
            smooth: 1,
            held: false,
            started: false,
            clipped: Vec::new(),
            ramp: (0.0, "default"),
        }
    }

    /// Stop the stream and hold the outputs where the stage stands.
    fn hold(&mut self, inst: &mut Instrument) -> Result<Pos, DeviceError> {
        self.run = None;
        let t = Instant::now();
        let r = stream_of(inst).and_then(|s| s.hold());
        self.ph.hold_s += t.elapsed().as_secs_f64();
        if let Ok(p) = r {
            self.at = Some(p);
        }
        r
    }

    /// Start the frame at line `i` from where the stage stands.
    fn start(&mut self, inst: &mut Instrument, rp: &RasterPlan, i: usize) -> Result<(), StepFault> {
        let geo = self.geo.expect("prepared");
        let t = Instant::now();
        let here = inst.stage.target().map_err(StepFault::stage)?;
        let frame = Frame::new(rp, &geo, i, [here[geo.fast], here[geo.slow]]);
        let total = frame.len + ((PAD_S * geo.rate) as usize).max(2);
        let first = ((AHEAD_S * geo.rate) as usize).max(2).min(total);
        let (mut f, mut s) = (Vec::with_capacity(first), Vec::with_capacity(first));
        frame.fill(rp, 0, first, &mut f, &mut s);
        while f.len() < first {
            f.push(frame.last[0]);
            s.push(frame.last[1]);
        }
        let stream = stream_of(inst).map_err(StepFault::stage)?;
        self.started = true;
        self.held = false;
        stream.start(&f, &s).map_err(StepFault::stage)?;
        self.ph.starts += 1;
        self.ph.frame_samples += frame.len;
        self.ph.buffer_samples = stream.buffer_samples();
        self.ph.start_s += t.elapsed().as_secs_f64();
        let (x0, y0) = (f[0], s[0]);
        self.run = Some(Running {
            written: f.len(),
            total,
            plan_lo: x0,
            plan_hi: x0,
            now_lo: [x0, y0],
            now_hi: [x0, y0],
            now_upto: 1,
            frame,
            read: 0,
            buf: StreamChunk::default(),
            base: 0,
            next: 0,
            t0: Instant::now(),
        });
        Ok(())
    }

    /// Keep the outputs written ahead of the inputs, then read one chunk.
    fn pump(
        &mut self,
        inst: &mut Instrument,
        rp: &RasterPlan,
        until: usize,
    ) -> Result<(), StepFault> {
        let geo = self.geo.expect("prepared");
        let ahead = (AHEAD_S * geo.rate) as usize;
        let chunk = ((CHUNK_S * geo.rate) as usize).max(1);
        let ph = &mut self.ph;
        let run = self.run.as_mut().expect("running");
        let stream = stream_of(inst).map_err(StepFault::stage)?;
        let guard_n = (GUARD_S * geo.rate) as usize;
        let guard_chunk = ((GUARD_CHUNK_S * geo.rate) as usize).max(1);
        while run.read < until {
            write_ahead(run, ph, stream, rp, &geo, ahead, chunk)?;
            let guarding = run.read < guard_n;
            let n = if guarding { guard_chunk } else { chunk }.min(until - run.read);
            if guarding {
                guard_by_readings(run, stream, rp, &geo, guard_chunk, n)?;
            }
            let timeout = n as f64 / geo.rate + 2.0;
            let t = Instant::now();
            let c = stream.read(n, timeout).map_err(StepFault::stage)?;
            ph.read_s += t.elapsed().as_secs_f64();
            ph.convert_s += c.convert_s;
            ph.reads += 1;
            if c.is_empty() {
                return Err(StepFault::stage(DeviceError::Other {
                    device: stream.stream_name(),
                    detail: format!(
                        "the inputs returned no sample after {} of {}",
                        run.read, until
                    ),
                }));
            }
            if guarding {
                // a lagging stage stays within the targets played so far: a measured
                // position outside them (with a margin) is a stage that runs away
                let (mut f, mut s) = (Vec::with_capacity(c.len()), Vec::with_capacity(c.len()));
                run.frame.fill(rp, run.read, c.len(), &mut f, &mut s);
                let mut away = None;
                for (j, &m) in c.fast_um.iter().enumerate() {
                    if let Some(&x) = f.get(j) {
                        run.plan_lo = run.plan_lo.min(x);
                        run.plan_hi = run.plan_hi.max(x);
                    }
                    if m < run.plan_lo - GUARD_UM || m > run.plan_hi + GUARD_UM {
                        away = Some((
                            AXES[geo.fast],
                            m,
                            format!(
                                "{:.2} ms into the stream (the sensor monitor)",
                                (run.read + j) as f64 / geo.rate * 1e3
                            ),
                            (run.plan_lo, run.plan_hi),
                        ));
                        break;
                    }
                }
                if let Some((axis, m, when, (lo, hi))) = away {
                    let wall_ms = run.t0.elapsed().as_secs_f64() * 1e3;
                    let advice = ran_away_advice(stream);
                    return Err(StepFault::stage(DeviceError::Other {
                        device: stream.stream_name(),
                        detail: format!(
                            "the stage ran away: {axis} reads {m:.3} µm {when}, where the plan had played \
                             {lo:.3}…{hi:.3} µm; the stream was stopped (seen {wall_ms:.1} ms after the outputs started){advice}"
                        ),
                    }));
                }
            }
            run.read += c.len();
            let due = (run.t0.elapsed().as_secs_f64() * geo.rate) as usize;
            ph.max_behind = ph.max_behind.max(due.saturating_sub(run.read));
            run.buf.sx.extend(c.sx);
            run.buf.sy.extend(c.sy);
            run.buf.sz.extend(c.sz);
            run.buf.fast_um.extend(c.fast_um);
            // clip flags: a prefix of the samples (the rest 0), padded when a chunk has some
            if !c.clipped.is_empty() {
                let before = run.buf.fast_um.len() - c.clipped.len();
                run.buf.clipped.resize(before, 0);
                run.buf.clipped.extend(c.clipped);
            }
        }
        Ok(())
    }

    fn line_step(&mut self, inst: &mut Instrument, rp: &RasterPlan, i: usize) -> StepResult {
        let expected = self
            .run
            .as_ref()
            .and_then(|r| r.frame.lines.get(r.next))
            .map(|l| l.0);
        if expected != Some(i) {
            if self.run.is_some() {
                self.hold(inst).map_err(StepFault::stage)?;
            }
            self.start(inst, rp, i)?;
        }
        let (line, s0, s1) = {
            let r = self.run.as_ref().expect("started");
            r.frame.lines[r.next]
        };
        self.pump(inst, rp, s1)?;
        let t = Instant::now();
        let run = self.run.as_mut().expect("running");
        let (a, b) = (s0 - run.base, s1 - run.base);
        let cols = &rp.cols;
        let device = inst.stage.name();
        let bad = |detail: String| {
            StepFault::other(DeviceError::Other {
                device: device.clone(),
                detail: format!("row {}: {detail}", line + 1),
            })
        };
        // the sensor monitor's noise (the board's input noise over its volts per µm: 0.5 mV
        // is 3.75 nm at 0.133 V/µm) is white from sample to sample, the stage's motion smooth
        // on the scale of its lag: a centred moving average over `smooth` samples takes the
        // noise down by √smooth and, at constant speed, leaves the position exact
        let smooth = self.smooth;
        let xs = moving_average(&run.buf.fast_um[a..b], smooth);
        let x = &xs[..];
        let (c0, c1) = (cols[0], cols[cols.len() - 1]);
        let bin = |v: &[f64]| bin_line(x, &v[a..b], c0, c1, cols.len()).map_err(bad);
        let bins = [bin(&run.buf.sx)?, bin(&run.buf.sy)?, bin(&run.buf.sz)?];
        self.stats.add_line(&bins[0], cols);
        if run.buf.clipped.len() > a {
            let flags = &run.buf.clipped[a..b.min(run.buf.clipped.len())];
            let counts = crate::acquire::clip::line_counts(x, flags, c0, c1, cols.len());
            self.clipped = crate::acquire::clip::line_pixels(rp.lines[line].row, &counts);
        }
        // the targets of the line's samples, for the lag
        let (mut tf, mut ts) = (Vec::with_capacity(b - a), Vec::with_capacity(b - a));
        run.frame.fill(rp, s0, s1 - s0, &mut tf, &mut ts);
        self.stats.add_lag(&tf, x, cols);
        if self.keep_raw {
            self.raw[0].push(run.buf.sx[a..b].to_vec());
            self.raw[1].push(run.buf.sy[a..b].to_vec());
            self.raw[2].push(run.buf.sz[a..b].to_vec());
            self.raw[3].push(run.buf.fast_um[a..b].to_vec());
            self.raw[4].push(tf);
        }
        // what is binned is dropped
        for v in [
            &mut run.buf.sx,
            &mut run.buf.sy,
            &mut run.buf.sz,
            &mut run.buf.fast_um,
        ] {
            v.drain(..b);
        }
        let k = b.min(run.buf.clipped.len());
        run.buf.clipped.drain(..k);
        run.base = s1;
        run.next += 1;
        let done = run.next == run.frame.lines.len();
        let stream_s = run.t0.elapsed().as_secs_f64();
        self.ph.bin_s += t.elapsed().as_secs_f64();
        self.ph.lines += 1;
        let geo = self.geo.expect("prepared");
        let mut end = self.base;
        end[geo.fast] = rp.lines[line].sweep.to_um;
        end[geo.slow] = rp.lines[line].start[geo.slow];
        self.at = Some(end);
        if done {
            // the lag measured on this frame sets the next frame's margins
            if let (Some(l), true) = (self.stats.lag_um_mean(), rp.speed_um_s > 0.0) {
                if let Ok(st) = stream_of(inst) {
                    st.record_lag_s(l / rp.speed_um_s);
                }
            }
            self.ph.stream_s += stream_s;
            self.hold(inst).map_err(StepFault::stage)?;
        }
        Ok((0..cols.len())
            .map(|c| (rp.lines[line].row, c, [0, 1, 2].map(|ch| bins[ch].mean[c])))
            .collect())
    }
}

/// The pre-flight of a streamed frame: every sample of the waveform inside the soft limits
/// (a block whose two extreme corners are inside is inside: the limits are a box), inside
/// what the outputs command (`range`, µm per axis, 0–10 V), and no faster than
/// `max_speed_um_s` — else the refusal names the sample and its time.
fn check_frame(
    who: &str,
    rp: &RasterPlan,
    geo: &Geometry,
    frame: &Frame,
    base: Pos,
    range: [(f64, f64); 2],
    limits: &SoftLimits,
) -> Result<(), ScanError> {
    let (rate, fast, slow) = (geo.rate, geo.fast, geo.slow);
    let block = 1 << 16;
    let (mut f, mut s) = (Vec::with_capacity(block), Vec::with_capacity(block));
    let mut prev: Option<[f64; 2]> = None;
    let mut k0 = 0;
    while k0 < frame.len {
        f.clear();
        s.clear();
        frame.fill(rp, k0, block, &mut f, &mut s);
        // the soft limits are a box: the block's two extreme corners inside, all inside
        let lo_hi = |v: &[f64]| {
            v.iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
                    (a.min(x), b.max(x))
                })
        };
        let ((x0, x1), (y0, y1)) = (lo_hi(&f), lo_hi(&s));
        let corner = |x: f64, y: f64| {
            let mut p = base;
            p[fast] = x;
            p[slow] = y;
            limits.check(p).is_ok()
        };
        let block_inside = corner(x0, y0) && corner(x1, y1);
        for (j, (&x, &y)) in f.iter().zip(&s).enumerate() {
            let k = k0 + j;
            let at = |k: usize| format!("sample {k} of the frame ({:.6} s)", k as f64 / rate);
            if !block_inside {
                let mut p = base;
                p[fast] = x;
                p[slow] = y;
                limits.check(p).map_err(|e| {
                    ScanError::Refused(format!(
                        "{who}: the waveform leaves the soft limits at {}: {}",
                        at(k),
                        e.0
                    ))
                })?;
            }
            for (i, v) in [x, y].into_iter().enumerate() {
                let (lo, hi) = range[i];
                if !(v >= lo - 1e-9 && v <= hi + 1e-9) {
                    return Err(ScanError::Refused(format!(
                        "{who}: the waveform's {} = {v:.4} µm at {} is outside what the output commands ({lo:.4}…{hi:.4} µm, 0–10 V)",
                        AXES[[fast, slow][i]],
                        at(k)
                    )));
                }
            }
            if let (Some(q), Some(max)) = (prev, limits.max_speed_um_s) {
                let v = (x - q[0]).hypot(y - q[1]) * rate;
                if v > max * (1.0 + 1e-6) {
                    return Err(ScanError::Refused(format!(
                        "{who}: the waveform moves at {v:.4} µm/s at {}, above max_speed_um_s = {max} µm/s",
                        at(k)
                    )));
                }
            }
            prev = Some([x, y]);
        }
        k0 += block;
    }
    Ok(())
}

impl Strategy for StreamStrategy {
    fn mode(&self) -> &'static str {
        "raster"
    }

    fn prepare(&mut self, inst: &mut Instrument, checked: &Checked) -> Result<Layout, ScanError> {
        let (plan, start, limits) = (checked.plan, checked.start, checked.limits);
        let kind = &plan.kind;
        let who = format!("{kind} (raster)");
        let settle_cfg = inst.settle_s;
        let stream = inst
            .stage
            .frame_stream()
            .ok_or_else(|| ScanError::Refused(format!("{who}: this stage has no frame stream")))?;
        // the ramps, margins and shortest turnarounds: as long as the stage's measured lag
        let lag = stream.lag_s();
        let settle_s = ramp_time(settle_cfg, lag);
        self.ramp = (settle_s, ramp_source(settle_cfg, lag));
        let name = stream.stream_name();
        let rate = stream.rate_hz();
        let (fast, slow) = stream.axes();
        let range = stream.output_range_um();
        let plan_fast = plan.fast.axis.index();
        let plan_slow = plan.slow.map(|s| s.axis.index());
        let Some(slow) = slow else {
            return Err(ScanError::Refused(format!(
                "{who}: {name} drives only {} (raster.ao has no y): a streamed frame steps its rows with the y output",
                AXES[fast]
            )));
        };
        if plan_fast != fast || plan_slow != Some(slow) {
            return Err(ScanError::Refused(format!(
                "{who}: {name} streams {} lines stepped in {} (scan_xy); this scan sweeps {}{}",
                AXES[fast],
                AXES[slow],
                AXES[plan_fast],
                plan_slow.map_or(String::new(), |s| format!(" stepped in {}", AXES[s]))
            )));
        }
        let spp = plan.dwell_s * rate;
        if spp < 1.0 {
            return Err(ScanError::Refused(format!(
                "{who}: dwell = {} s is shorter than one sample of the board at {rate} S/s: use a dwell ≥ {:.3e} s",
                plan.dwell_s,
                1.0 / rate
            )));
        }
        let timing = LineTiming {
            servo_cycle_s: 1.0 / rate,
            max_wave_points: usize::MAX / 4,
            max_record_points: usize::MAX / 4,
            trigger_line: None,
        };
        let rp = checked.raster_lines(&timing, settle_s)?;
        let geo = Geometry {
            rate,
            settle_s,
            max_speed: limits.max_speed_um_s,
            fast,
            slow,
        };
        // pre-flight: every sample of the frame (from where the stage stands), in µm
        let here = [start[fast], start[slow]];
        let frame = Frame::new(&rp, &geo, 0, here);
        let base = plan.base(start);
        check_frame(&who, &rp, &geo, &frame, base, range, limits)?;
        let n_lines = rp.lines.len();
        let per_line = frame.len as f64 / rate / n_lines as f64;
        let turn_s = (frame.len - frame.lines.iter().map(|l| l.2 - l.1).sum::<usize>()) as f64
            / rate
            / n_lines as f64;
        let eta_detail = format!(
            "one frame streamed at {rate} S/s: {n_lines} lines of {} pixels at {:.4} µm/s ({} per pixel, {:.1} samples), line {} incl. ramps and margins {}, turnaround {}",
            rp.cols.len(),
            rp.speed_um_s,
            fmt_seconds(plan.dwell_s),
            spp,
            fmt_seconds(rp.line_s),
            fmt_seconds(rp.turnaround_s),
            fmt_seconds(turn_s),
        );
        self.smooth = smoothing_samples(rate, settle_s);
        self.keep_raw = frame.len <= RAW_MAX_SAMPLES;
        self.dwell_s = plan.dwell_s;
        self.base = base;
        self.geo = Some(geo);
        self.rp = Some(Arc::new(rp));
        self.stats.sample_rate = Some(rate);
        Ok(Layout {
            steps: n_lines,
            steps_per_row: 1,
            unit: "line",
            step_s: per_line,
            eta_detail,
        })
    }

    line_by_line_steps!();

    fn pause(&mut self, inst: &mut Instrument) -> Result<(), DeviceError> {
        if let Some(r) = &self.run {
            self.ph.stream_s += r.t0.elapsed().as_secs_f64();
        }
        self.hold(inst).map(|_| self.held = true)
    }

    fn stop(&mut self, inst: &mut Instrument, _cause: StopCause) -> Option<Result<String, String>> {
        if !self.started {
            return None;
        }
        let row = self.ph.lines;
        if self.held && self.run.is_none() {
            return Some(Ok(format!(
                "the stream was stopped and the outputs held at the pause after line {row}"
            )));
        }
        if let Some(r) = &self.run {
            self.ph.stream_s += r.t0.elapsed().as_secs_f64();
        }
        let name = inst.stage.name();
        // the outputs drive the stage: holding them is its stop; the Nano-Drive's own stop
        // (hold at its reading) only when they could not be held
        Some(match self.hold(inst) {
            Ok(p) => Ok(format!(
                "the stream was stopped after line {row} and the outputs hold {name} at x = {:.4}, y = {:.4} µm",
                p[0], p[1]
            )),
            Err(e) => match inst.stage.stop() {
                Ok(()) => Err(format!(
                    "stopping the stream and holding the outputs failed ({e}); {name} was held at its reading"
                )),
                Err(e2) => Err(format!(
                    "stopping the stream failed: {e}; holding {name} failed too: {e2}"
                )),
            },
        })
    }

    fn metadata(
        &mut self,
        _inst: &mut Instrument,
        _steps: usize,
        loop_s: f64,
        log: &dyn Fn(&str),
    ) -> Value {
        let (Some(rp), Some(geo)) = (self.rp.as_ref(), self.geo) else {
            return json!({});
        };
        let ph = &self.ph;
        let n_lines = ph.lines.max(1) as f64;
        let ms = |s: f64| s / n_lines * 1e3;
        let cpu = ph.convert_s + ph.bin_s;
        let share = if ph.stream_s > 0.0 {
            cpu / ph.stream_s
        } else {
            0.0
        };
        let mut m = json!({
            "lines_measured": ph.lines,
            "raster": {
                "path": "frame stream",
                "line_speed_um_s": rp.speed_um_s,
                "dwell_s": self.dwell_s,
                "line_s": rp.line_s,
                "turnaround_s": rp.turnaround_s,
                "samples_per_pixel_asked": self.opts.samples_per_pixel,
                "samples_per_pixel_board": self.dwell_s * geo.rate,
                "position_smoothing_samples": self.smooth,
                "ramp_s": self.ramp.0,
                "ramp_from": self.ramp.1,
                "lag_s_measured": self.stats.lag_um_mean().filter(|_| rp.speed_um_s > 0.0).map(|l| l / rp.speed_um_s),
                "duty_cycle": (ph.stream_s > 0.0).then(|| ph.lines as f64 * rp.cols.len() as f64 * self.dwell_s / ph.stream_s),
                "raw_kept": self.keep_raw,
                "binning": "each pixel: the board's samples whose measured fast-axis position (the sensor monitor, sampled on the same clock) lies within half a pitch of its centre; its value is their least-squares line (value against position) at the centre",
                "stream": {
                    "frames_started": ph.starts,
                    "frame_samples": ph.frame_samples,
                    "frame_s": ph.frame_samples as f64 / geo.rate,
                    "buffer_samples": ph.buffer_samples,
                    "max_behind_samples": ph.max_behind,
                    "writes": ph.writes,
                    "max_write_ms": ph.max_write_s * 1e3,
                    "reads": ph.reads,
                    "stream_s": ph.stream_s,
                    "binning_cpu_s": cpu,
                    "binning_cpu_share": share,
                },
            },
            "time": {
                "lines": {
                    "start_ms": ms(ph.start_s),
                    "write_ms": ms(ph.write_s),
                    "read_ms": ms(ph.read_s),
                    "convert_ms": ms(ph.convert_s),
                    "bin_ms": ms(ph.bin_s),
                    "hold_ms": ms(ph.hold_s),
                }
            },
        });
        self.stats.merge_into(&mut m["raster"]);
        if ph.lines > 0 {
            log(&format!(
                "streamed {} samples per channel (each output and each input) in {} (loop {}); converting and binning took {:.1} % of one core",
                ph.frame_samples,
                fmt_seconds(ph.stream_s),
                fmt_seconds(loop_s),
                100.0 * share
            ));
        }
        m
    }

    fn raw(&mut self) -> Vec<(String, Array2<f64>)> {
        if !self.keep_raw {
            return Vec::new();
        }
        let rows = self.rp.as_ref().map_or(0, |rp| rp.lines.len());
        ["sx", "sy", "sz", "position_um", "target_um"]
            .iter()
            .zip(&self.raw)
            .map(|(n, v)| (n.to_string(), padded(v, rows)))
            .collect()
    }
}

/// The window of the position's moving average (samples, odd): a hundredth of the settle time
/// (the settle time is about five time constants τ of the stage's lag). During a speed change
/// of the lag's acceleration v/τ, a window of T s shifts the position by ≈ (v/τ)·T²/24: with
/// T = 5τ/100 that is v·τ/9600, 0.2 nm for a lag v·τ of 2 µm, while the noise drops by
/// √(rate·T) (9 samples at 800 kS/s and 1 ms settle: 3×; 81 at 10 ms: 9×).
pub fn smoothing_samples(rate_hz: f64, settle_s: f64) -> usize {
    let n = (rate_hz * settle_s / 100.0).round().max(1.0) as usize;
    n | 1
}

/// Centred moving average of `x` over `w` samples (odd), the window shrinking symmetrically at
/// the ends.
pub fn moving_average(x: &[f64], w: usize) -> Vec<f64> {
    let h = w / 2;
    let n = x.len();
    let mut cum = Vec::with_capacity(n + 1);
    cum.push(0.0);
    for &v in x {
        cum.push(cum.last().copied().unwrap_or(0.0) + v);
    }
    (0..n)
        .map(|i| {
            let r = h.min(i).min(n - 1 - i);
            (cum[i + r + 1] - cum[i - r]) / (2 * r + 1) as f64
        })
        .collect()
}

/// Keep the outputs `ahead` samples ahead of the clock (see `StreamStrategy::pump`).
fn write_ahead(
    run: &mut Running,
    ph: &mut Phases,
    stream: &mut dyn FrameStream,
    rp: &RasterPlan,
    geo: &Geometry,
    ahead: usize,
    chunk: usize,
) -> Result<(), StepFault> {
    // the outputs are kept `ahead` of the clock (the samples it has played by now,
    // estimated from the stream's start), whatever the inputs' reader lags; a write
    // brings only what the buffer takes now, so that it never waits for room
    let played = ((run.t0.elapsed().as_secs_f64() * geo.rate) as usize).max(run.read);
    if run.written < run.total && run.written < played + ahead {
        let mut n = (played + ahead - run.written).min(run.total - run.written);
        if let Some(space) = stream.write_space().map_err(StepFault::stage)? {
            n = n.min(space);
        }
        // not a trickle of tiny writes: a chunk at least (or what is left)
        if n >= chunk.min(run.total - run.written) {
            let t = Instant::now();
            let (mut f, mut s) = (Vec::with_capacity(n), Vec::with_capacity(n));
            let in_frame = run.frame.len.saturating_sub(run.written).min(n);
            run.frame.fill(rp, run.written, in_frame, &mut f, &mut s);
            f.resize(n, run.frame.last[0]);
            s.resize(n, run.frame.last[1]);
            stream.write(&f, &s).map_err(StepFault::stage)?;
            run.written += n;
            let dt = t.elapsed().as_secs_f64();
            ph.write_s += dt;
            ph.max_write_s = ph.max_write_s.max(dt);
            ph.writes += 1;
        }
    }
    Ok(())
}

/// In the stream's first milliseconds, until the inputs hold the next `n` samples: the stage's
/// own readings against the targets played by now (a run-away is an error naming the cause).
fn guard_by_readings(
    run: &mut Running,
    stream: &mut dyn FrameStream,
    rp: &RasterPlan,
    geo: &Geometry,
    guard_chunk: usize,
    n: usize,
) -> Result<(), StepFault> {
    // Until the inputs have the next chunk, the stage's own readings (Madlib: a
    // USB round trip each, back to back) against the targets played by now: no
    // sleep in a blocking read, whose wake-up a loaded host delays by
    // milliseconds, stands between a run-away and its stop.
    loop {
        let elapsed = run.t0.elapsed().as_secs_f64();
        let played = (elapsed * geo.rate) as usize;
        // the targets up to a millisecond ahead of the estimate (the outputs
        // started a little before it)
        let upto = (played + guard_chunk + (1e-3 * geo.rate) as usize).min(run.written);
        if upto > run.now_upto {
            let (mut f, mut s) = (Vec::new(), Vec::new());
            run.frame
                .fill(rp, run.now_upto, upto - run.now_upto, &mut f, &mut s);
            for (k, v) in [f, s].iter().enumerate() {
                for &x in v {
                    run.now_lo[k] = run.now_lo[k].min(x);
                    run.now_hi[k] = run.now_hi[k].max(x);
                }
            }
            run.now_upto = upto;
        }
        let mut away = None;
        for (k, axis) in [geo.fast, geo.slow].into_iter().enumerate() {
            let Some(m) = stream.guard_position_um(axis).map_err(StepFault::stage)? else {
                continue;
            };
            let (lo, hi) = (run.now_lo[k], run.now_hi[k]);
            if m < lo - GUARD_UM || m > hi + GUARD_UM {
                away = Some((axis, m, lo, hi));
                break;
            }
        }
        if let Some((axis, m, lo, hi)) = away {
            let wall_ms = elapsed * 1e3;
            let advice = ran_away_advice(stream);
            return Err(StepFault::stage(DeviceError::Other {
                device: stream.stream_name(),
                detail: format!(
                    "the stage ran away: it reads {} = {m:.3} µm {wall_ms:.2} ms into the stream, where the plan \
                     had played {lo:.3}…{hi:.3} µm; the stream was stopped{advice}",
                    AXES[axis]
                ),
            }));
        }
        // no reading of its own (nothing to watch but the inputs), or the chunk is in
        if !stream.guards_by_reading() || played >= run.read + n {
            break;
        }
    }
    Ok(())
}

/// The stream's stop on a run-away (`FrameStream::ran_away`), and its advice as the tail of the
/// fault's message ("; …", empty without advice).
fn ran_away_advice(stream: &mut dyn FrameStream) -> String {
    let advice = stream.ran_away();
    if advice.is_empty() {
        String::new()
    } else {
        format!("; {advice}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::acquire::raster::RasterLine;
    use crate::instrument::line::LineSweep;

    fn plan2(n_lines: usize) -> RasterPlan {
        let sweep = |from: f64, to: f64| LineSweep {
            axis: 0,
            from_um: from,
            to_um: to,
            points: 11,
            speedupdown: 2,
            rate: 1,
            record_rate: 1,
            trigger_line: None,
            table: 1,
            servo_cycle_s: 1e-3,
        };
        RasterPlan {
            lines: (0..n_lines)
                .map(|r| RasterLine {
                    row: r,
                    start: [1.0, 2.0 + r as f64, 5.0],
                    sweep: sweep(1.0, 3.0),
                })
                .collect(),
            cols: vec![1.5, 2.0, 2.5],
            rows: (0..n_lines).map(|r| 2.0 + r as f64).collect(),
            speed_um_s: 250.0,
            line_s: 0.011,
            turnaround_s: 0.008,
        }
    }

    /// The frame is continuous: each line's wave where the plan puts it, turnarounds that
    /// start and end on the neighbouring samples with zero speed, the slow axis constant
    /// along a line; filling in any blocks gives the same samples.
    #[test]
    fn a_frame_joins_the_lines_with_turnarounds_at_rest_at_both_ends() {
        let rp = plan2(3);
        let geo = Geometry {
            rate: 1000.0,
            settle_s: 0.005,
            max_speed: Some(100.0),
            fast: 0,
            slow: 1,
        };
        let fr = Frame::new(&rp, &geo, 0, [0.0, 0.0]);
        let (mut f, mut s) = (vec![], vec![]);
        fr.fill(&rp, 0, fr.len, &mut f, &mut s);
        assert_eq!(f.len(), fr.len);
        assert_eq!((f[0], s[0]), (0.0, 0.0));
        for &(line, a, b) in &fr.lines {
            let w = rp.lines[line].sweep.wave();
            assert_eq!(&f[a..b], &w[..], "line {line}");
            assert!(s[a..b].iter().all(|&y| y == 2.0 + line as f64));
        }
        // the first turnaround: distance hypot(1, 2) at ≤ 100 µm/s: π/2·√5/100 s = 35.1 ms
        let n0 = fr.lines[0].1;
        assert_eq!(
            n0,
            (std::f64::consts::FRAC_PI_2 * 5f64.sqrt() / 100.0 * 1000.0).ceil() as usize
        );
        // no step between samples faster than the limit anywhere
        for k in 1..f.len() {
            let v = (f[k] - f[k - 1]).hypot(s[k] - s[k - 1]) * geo.rate;
            assert!(
                v <= 100.0 + 1e-9 || (f[k] - f[k - 1]).abs() * geo.rate <= 250.0 + 1e-9,
                "{k}: {v}"
            );
        }
        // blocks of 7 give the same samples
        let (mut f7, mut s7) = (vec![], vec![]);
        let mut k = 0;
        while k < fr.len {
            fr.fill(&rp, k, 7, &mut f7, &mut s7);
            k += 7;
        }
        assert_eq!(f7, f);
        assert_eq!(s7, s);
        assert_eq!(fr.last, [3.0, 4.0]);
    }

    /// The moving average keeps a constant-speed ramp exactly (also at the ends, where the
    /// window shrinks symmetrically) and takes white noise down by √w.
    #[test]
    fn the_moving_average_keeps_a_ramp_and_shrinks_noise() {
        let ramp: Vec<f64> = (0..50).map(|k| 1.0 + 0.25 * k as f64).collect();
        let m = moving_average(&ramp, 9);
        for (a, b) in m.iter().zip(&ramp) {
            assert!((a - b).abs() < 1e-12, "{a} vs {b}");
        }
        // ±1 alternating (white at the Nyquist rate): the 9-sample mean is ±1/9
        let alt: Vec<f64> = (0..40)
            .map(|k| if k % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        let m = moving_average(&alt, 9);
        assert!(m[4..36].iter().all(|v| (v.abs() - 1.0 / 9.0).abs() < 1e-12));
        assert_eq!(smoothing_samples(800_000.0, 0.001), 9);
        assert_eq!(smoothing_samples(800_000.0, 0.01), 81);
        assert_eq!(smoothing_samples(1000.0, 0.001), 1);
    }

    /// A turnaround's peak speed is π/2 · distance / duration: at the limit when the distance
    /// decides, and the settle time when it is short.
    #[test]
    fn turnaround_length_follows_the_speed_limit_or_the_settle_time() {
        let geo = Geometry {
            rate: 1e5,
            settle_s: 0.002,
            max_speed: Some(1000.0),
            fast: 0,
            slow: 1,
        };
        // 10 µm at ≤ 1000 µm/s: 15.708 ms
        assert_eq!(geo.turn_samples([0.0, 0.0], [10.0, 0.0]), 1571);
        // 0.1 µm: the settle time, 2 ms
        assert_eq!(geo.turn_samples([0.0, 0.0], [0.0, 0.1]), 200);
        let free = Geometry {
            max_speed: None,
            ..geo
        };
        assert_eq!(free.turn_samples([0.0, 0.0], [10.0, 0.0]), 200);
    }
}
