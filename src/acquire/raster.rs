//! Hardware-timed raster scans (`scan_xy(#{…, mode: "raster"})`): the fast axis sweeps each
//! line at constant speed under the controller's clock (a wave generator), the controller's
//! trigger output starts the digitiser, the data recorder gives the measured position of the
//! stage, and each line's digitiser samples are binned into pixels by that *measured* position
//! (docs/hardware.md §10).
//!
//! The engine ([`run_raster`]) keeps every rule of the point-by-point engine and extends the
//! stop rule to the wave generator:
//! 1. pre-flight: every pixel and the whole waveform (ramps and margins included) against the
//!    soft limits, and the line speed (pitch / dwell) against the speed limit, before the
//!    first move; a refused plan moves nothing;
//! 2. ETA (per line: the move to the line's start, settle, the wave, the reads) and progress
//!    per line;
//! 3. per line: arm the digitiser on the external trigger; move to the wave's first point
//!    (no settle: the wave's speed-up ramp of `settle` s and its margin of `settle` s at line
//!    speed pass before the first pixel); configure the line (once, when lines repeat); start
//!    the wave; wait for it; read the digitiser and the recorder; bin;
//! 4. Ctrl-C or any fault: the digitiser stopped, the wave generator and the axes stopped
//!    (PI: `WGO g 0`, `STP`), the completed lines saved (later rows NaN), no further motion
//!    (not even the return of a relative scan);
//! 5. the scan file keeps the raw samples beside the binned image (`Scan::raw`) and records
//!    the line speed, samples per pixel and the position error in `meta.raster`.
//!
//! Conventions: positions in µm, times in s. A line of `n` pixels from `from` to `to` has its
//! pixel centres at `from + i·w`, `w = (to − from)/(n − 1)` (as the point-by-point scans), and
//! pixel `i` takes the samples whose measured position lies within `w/2` of its centre
//! (half-open: `[c − w/2, c + w/2)` in the sweep direction).

use super::engine::{
    finish, progress_bar, Ended, ScanClock, ScanEnv, ScanError, ScanRun, ScanStart,
};
use super::limits::SoftLimits;
use super::plan::{fmt_seconds, Plan};
use crate::data::{Image, Scan};
use crate::instrument::line::{LineSweep, LineTiming, SweepRecord};
use crate::instrument::{BufferedTrace, DeviceError, Instrument, Pos, Trigger};
use ndarray::Array2;
use serde_json::json;
use std::sync::atomic::Ordering;

/// Digitiser samples asked per pixel (the digitiser may give more: its rates are steps).
pub const DEFAULT_SAMPLES_PER_PIXEL: usize = 20;

/// Data-recorder samples per pixel (at least one per servo cycle when pixels are shorter).
const RECORD_PER_PIXEL: f64 = 4.0;

/// One line of a raster: the row it fills, where the other axes stand, and the wave.
#[derive(Debug, Clone, PartialEq)]
pub struct RasterLine {
    pub row: usize,
    /// The stage position at the wave's first point (µm).
    pub start: Pos,
    pub sweep: LineSweep,
}

/// The lines of a raster plan and what they imply.
#[derive(Debug, Clone, PartialEq)]
pub struct RasterPlan {
    pub lines: Vec<RasterLine>,
    /// Pixel centres along the fast axis, image order (µm).
    pub cols: Vec<f64>,
    /// Row positions (µm).
    pub rows: Vec<f64>,
    /// Constant line speed, µm/s: pitch / dwell.
    pub speed_um_s: f64,
    /// Wave duration per line, s (ramps and margins included).
    pub line_s: f64,
    /// Time of a line not spent on its pixels (ramps, margins), s.
    pub turnaround_s: f64,
}

/// The waves of `plan` (a 2-D grid, ≥ 2 columns) for a stage with `timing`: each line sweeps
/// the fast axis at `speed = pitch / dwell` over its pixels' bins (`[c₀ − w/2, c_last + w/2]`)
/// plus a margin of `speed · settle_s` at each end, for the stage's lag to settle, with speed
/// ramps of `settle_s` (at least 4 servo cycles) outside. Snake plans alternate the direction.
/// The whole waveform is checked against `limits` and the line speed against its speed limit.
pub fn plan_lines(
    plan: &Plan,
    start: Pos,
    timing: &LineTiming,
    settle_s: f64,
    limits: &SoftLimits,
) -> Result<RasterPlan, String> {
    let who = format!("{} (raster)", plan.kind);
    let dt = timing.servo_cycle_s;
    if !(dt.is_finite() && dt > 0.0) {
        return Err(format!(
            "{who}: the controller's servo cycle {dt} s is not usable"
        ));
    }
    if plan.slow.is_none() || plan.with.is_some() {
        return Err(format!(
            "{who}: mode \"raster\" is for 2-D scans (scan_xy, scan_xz, scan_yz)"
        ));
    }
    let cols = plan.col_positions(start);
    let n = cols.len();
    if n < 2 {
        return Err(format!(
            "{who}: {} columns: a raster line needs at least 2 pixels",
            n
        ));
    }
    let rows = plan.row_positions(start);
    let pitch = (cols[n - 1] - cols[0]) / (n - 1) as f64;
    if pitch == 0.0 {
        return Err(format!("{who}: the fast axis range is empty (from = to)"));
    }
    let v = pitch.abs() / plan.dwell_s;
    if let Some(max) = limits.max_speed_um_s {
        if v > max * (1.0 + 1e-12) {
            return Err(format!(
                "{who}: line speed {v:.4} µm/s (pitch {:.4} µm / dwell {} s) exceeds max_speed_um_s = {max} µm/s; \
                 use a dwell ≥ {:.3e} s or a finer pitch",
                pitch.abs(),
                plan.dwell_s,
                pitch.abs() / max
            ));
        }
    }
    let ramp_cycles = ((settle_s / dt).ceil() as usize).max(4);
    let margin = v * settle_s;
    let cover = (cols[n - 1] - cols[0]).abs() + pitch.abs() + 2.0 * margin;
    // servo cycles per wave point: the wave must fit one table
    let mut rate = 1u32;
    let (points, amp, s_pts) = loop {
        let v_pt = v * f64::from(rate) * dt;
        let s_pts = ramp_cycles.div_ceil(rate as usize).max(1);
        let t = 2 * s_pts + (cover / v_pt).ceil() as usize;
        let points = t + 1;
        if points <= timing.max_wave_points {
            break (points, v_pt * (t - s_pts) as f64, s_pts);
        }
        if rate > 1 << 16 {
            return Err(format!(
                "{who}: a line of {:.1} s does not fit the wave table of {} points",
                points as f64 * f64::from(rate) * dt,
                timing.max_wave_points
            ));
        }
        rate = rate.saturating_mul(2);
    };
    // the recorder: about 4 samples per pixel (a constant-speed line is linear between
    // them; on the ramps, interpolating the lagged position between samples h apart errs by
    // a·h²/8 ≈ 0.1 nm at 50 µm/s, 5 ms ramps, h = 0.25 ms), and no more than a table holds;
    // every servo cycle would cost 20 bytes per 50 µs on the link (a 115200-baud `DRR?` of a
    // 64-pixel line at 1 ms: 3 s)
    let cycles = points as u64 * u64::from(rate);
    let fit_table = cycles
        .div_ceil(timing.max_record_points.max(1) as u64)
        .max(1);
    let per_pixel = ((plan.dwell_s / (RECORD_PER_PIXEL * dt)).floor() as u64).max(1);
    let record_rate = fit_table.max(per_pixel).min(u64::from(u32::MAX)) as u32;
    let axis = plan.fast.axis.index();
    let centre = 0.5 * (cols[0] + cols[n - 1]);
    let base = plan.base(start);
    let slow = plan.slow.map(|s| s.axis.index()).unwrap_or(axis);
    let mut lines = Vec::with_capacity(rows.len());
    for (r, &y) in rows.iter().enumerate() {
        let forward = !(plan.snake && r % 2 == 1);
        let dir = pitch.signum() * if forward { 1.0 } else { -1.0 };
        let (from_um, to_um) = (centre - dir * amp / 2.0, centre + dir * amp / 2.0);
        let mut p0 = base;
        p0[slow] = y;
        p0[axis] = from_um;
        let mut p1 = p0;
        p1[axis] = to_um;
        for (what, p) in [("start", p0), ("end", p1)] {
            limits.check(p).map_err(|e| {
                format!(
                    "{who}: the wave of row {} ({what}, ramps and margins included) leaves the soft limits: {}",
                    r + 1,
                    e.0
                )
            })?;
        }
        lines.push(RasterLine {
            row: r,
            start: p0,
            sweep: LineSweep {
                axis,
                from_um,
                to_um,
                points,
                speedupdown: s_pts,
                rate,
                record_rate,
                trigger_line: timing.trigger_line,
                table: 1,
                servo_cycle_s: dt,
            },
        });
    }
    let line_s = lines[0].sweep.duration_s();
    Ok(RasterPlan {
        lines,
        cols,
        rows,
        speed_um_s: v,
        line_s,
        turnaround_s: line_s - n as f64 * plan.dwell_s,
    })
}

/// A line binned into pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct LineBins {
    /// The pixel's value at its centre: the least-squares line through its samples (value
    /// against measured position) evaluated at the centre. That is the samples' mean, moved
    /// to the centre along the local slope: where the samples fall in a pixel depends on the
    /// digitiser's phase (up to half a sample spacing off centre, the same way on every line
    /// of a one-way raster), and the plain mean would shift the image by that much. A pixel
    /// with one sample, or samples all at one position, takes their mean.
    pub mean: Vec<f64>,
    /// Samples per pixel.
    pub count: Vec<usize>,
    /// Mean measured position of the samples per pixel, µm (its distance from the pixel's
    /// centre is the residual position error of the binning).
    pub position: Vec<f64>,
}

/// The stage position at each digitiser sample: the recorder's positions (`record`, one per
/// `record_dt` s from the generator's start) interpolated linearly at `t = delay + k·sample_dt`
/// for `k = 0 … n − 1` (`delay`: the digitiser's first sample after the generator's start,
/// s). `Err` when a sample falls outside the record or an argument is not usable.
pub fn positions_at_samples(
    record: &[f64],
    record_dt: f64,
    n: usize,
    sample_dt: f64,
    delay: f64,
) -> Result<Vec<f64>, String> {
    if record.len() < 2 {
        return Err(format!(
            "record of {} points: at least 2 are needed",
            record.len()
        ));
    }
    for (name, v) in [("record_dt", record_dt), ("sample_dt", sample_dt)] {
        if !(v.is_finite() && v > 0.0) {
            return Err(format!("{name} = {v} s: must be finite and > 0"));
        }
    }
    if !(delay.is_finite() && delay >= 0.0) {
        return Err(format!("delay = {delay} s: must be finite and ≥ 0"));
    }
    let last = (record.len() - 1) as f64;
    (0..n)
        .map(|k| {
            let u = (delay + k as f64 * sample_dt) / record_dt;
            if u > last + 1e-9 {
                return Err(format!(
                    "digitiser sample {k} at {:.6} s is after the record's end at {:.6} s",
                    u * record_dt,
                    last * record_dt
                ));
            }
            let i = (u.floor() as usize).min(record.len() - 2);
            let f = (u - i as f64).clamp(0.0, 1.0);
            Ok(record[i] + f * (record[i + 1] - record[i]))
        })
        .collect()
}

/// Bin `values` (one per sample) by their measured `positions` into `n` pixels from `from`
/// to `to` (µm). Samples outside the line (speed-up, speed-down, lag) are left out. `Err`
/// names a pixel without samples (the line was too fast for the digitiser) or a bad argument.
pub fn bin_line(
    positions: &[f64],
    values: &[f64],
    from: f64,
    to: f64,
    n: usize,
) -> Result<LineBins, String> {
    if positions.len() != values.len() {
        return Err(format!(
            "{} positions for {} samples",
            positions.len(),
            values.len()
        ));
    }
    if n < 2 {
        return Err(format!("n = {n} pixels: at least 2"));
    }
    if !(from.is_finite() && to.is_finite()) || from == to {
        return Err(format!(
            "line from {from} to {to} µm: must be finite and distinct"
        ));
    }
    let w = (to - from) / (n - 1) as f64;
    let mut sum = vec![0.0; n];
    let mut pos = vec![0.0; n];
    let mut count = vec![0usize; n];
    let pixel = |x: f64| {
        let u = (x - from) / w + 0.5;
        (u >= 0.0 && u < n as f64).then_some(u as usize)
    };
    let valid = |x: f64, v: f64| x.is_finite() && v.is_finite();
    for (&x, &v) in positions.iter().zip(values) {
        if let Some(i) = pixel(x).filter(|_| valid(x, v)) {
            sum[i] += v;
            pos[i] += x;
            count[i] += 1;
        }
    }
    // second pass, centred sums: slope = Σ(x − x̄)(v − v̄) / Σ(x − x̄)²
    let mean_x: Vec<f64> = (0..n).map(|i| pos[i] / count[i].max(1) as f64).collect();
    let mean_v: Vec<f64> = (0..n).map(|i| sum[i] / count[i].max(1) as f64).collect();
    let mut sxx = vec![0.0; n];
    let mut sxv = vec![0.0; n];
    for (&x, &v) in positions.iter().zip(values) {
        if let Some(i) = pixel(x).filter(|_| valid(x, v)) {
            let dx = x - mean_x[i];
            sxx[i] += dx * dx;
            sxv[i] += dx * (v - mean_v[i]);
        }
    }
    if let Some(i) = count.iter().position(|&c| c == 0) {
        return Err(format!(
            "pixel {i} (centre {:.4} µm) got no sample: the line is too fast for the digitiser's rate",
            from + i as f64 * w
        ));
    }
    let mean = (0..n)
        .map(|i| {
            let centre = from + i as f64 * w;
            // the samples' spread must resolve a slope: not one sample, not one position
            if count[i] < 2 || sxx[i] <= 1e-24 * w * w * count[i] as f64 {
                mean_v[i]
            } else {
                mean_v[i] + sxv[i] / sxx[i] * (centre - mean_x[i])
            }
        })
        .collect();
    Ok(LineBins {
        mean,
        position: mean_x,
        count,
    })
}

/// Options of a raster scan.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RasterOptions {
    /// Digitiser samples asked per pixel.
    pub samples_per_pixel: usize,
}

impl Default for RasterOptions {
    fn default() -> Self {
        RasterOptions {
            samples_per_pixel: DEFAULT_SAMPLES_PER_PIXEL,
        }
    }
}

/// One line measured: the binned row and what was binned.
struct LineData {
    bins: [LineBins; 3],
    trace: BufferedTrace,
    positions: Vec<f64>,
    record: SweepRecord,
}

/// Wall time per line by phase (real-time instruments), s summed; and the line the
/// controller holds.
#[derive(Default)]
struct LinePhases {
    configured: Option<LineSweep>,
    lines: usize,
    move_s: f64,
    configure_s: f64,
    wave_s: f64,
    qpd_s: f64,
    record_s: f64,
}

/// Arm the digitiser for line `s` on the controller's trigger (before the move to the line's
/// start: the trigger comes only with the wave).
fn arm(
    inst: &mut Instrument,
    s: &LineSweep,
    opts: &RasterOptions,
    dwell_s: f64,
) -> Result<(), DeviceError> {
    let rate = opts.samples_per_pixel as f64 / dwell_s;
    let n = (s.duration_s() * rate).ceil() as usize + 1;
    inst.qpd
        .arm_buffered(n, rate, Trigger::ExternalRising)
        .map(|_| ())
}

/// Measure one line (armed, the stage at rest on its first point). Any error: the caller stops.
fn measure_line(
    inst: &mut Instrument,
    l: &RasterLine,
    cols: &[f64],
    env: &ScanEnv,
    ph: &mut LinePhases,
) -> Result<Option<LineData>, DeviceError> {
    let s = &l.sweep;
    let t = std::time::Instant::now();
    // the same wave as the last line's (one-way rasters: the slow axis is set by the move to
    // the line's start): the controller keeps it, the recorder restarts with the generator
    if ph.configured.as_ref() != Some(s) {
        ph.configured = None;
        inst.stage.configure_line(s)?;
        ph.configured = Some(s.clone());
    }
    ph.configure_s += t.elapsed().as_secs_f64();
    let t = std::time::Instant::now();
    inst.stage.start_line(s)?;
    let played = inst.stage.wait_line(s, env.abort)?;
    ph.wave_s += t.elapsed().as_secs_f64();
    if !played {
        return Ok(None);
    }
    let t = std::time::Instant::now();
    let timeout = std::time::Duration::from_secs_f64(s.duration_s() + 2.0);
    let trace = inst.qpd.read_buffered(timeout)?;
    ph.qpd_s += t.elapsed().as_secs_f64();
    let t = std::time::Instant::now();
    let record = inst.stage.read_line_record(s)?;
    ph.record_s += t.elapsed().as_secs_f64();
    let bad = |detail: String| DeviceError::Other {
        device: format!("{} + {}", inst.qpd.name(), inst.stage.name()),
        detail,
    };
    // samples after the record's end have no measured position: left out
    let rec_end = (record.position_um.len().max(1) - 1) as f64 * record.sample_time_s;
    let keep = (0..trace.len())
        .take_while(|&k| trace.time(k) <= rec_end + 1e-12)
        .count();
    let positions = positions_at_samples(
        &record.position_um,
        record.sample_time_s,
        keep,
        trace.dt_s,
        trace.t0_s,
    )
    .map_err(|e| bad(format!("row {}: {e}", l.row + 1)))?;
    let (c0, c1) = (cols[0], cols[cols.len() - 1]);
    let bin = |v: &[f64]| {
        bin_line(&positions, &v[..keep], c0, c1, cols.len())
            .map_err(|e| bad(format!("row {}: {e}", l.row + 1)))
    };
    let bins = [bin(&trace.sx)?, bin(&trace.sy)?, bin(&trace.sz)?];
    Ok(Some(LineData {
        bins,
        trace,
        positions,
        record,
    }))
}

/// Rows × longest of `rows`, NaN-padded.
fn padded(rows: &[Vec<f64>], n_rows: usize) -> Array2<f64> {
    let w = rows.iter().map(Vec::len).max().unwrap_or(0);
    let mut a = Array2::from_elem((n_rows, w), f64::NAN);
    for (r, v) in rows.iter().enumerate() {
        for (k, &x) in v.iter().enumerate() {
            a[[r, k]] = x;
        }
    }
    a
}

/// Run `plan` as a hardware-timed raster on `inst`. See the module documentation.
pub fn run_raster(
    inst: &mut Instrument,
    plan: &Plan,
    opts: &RasterOptions,
    env: &ScanEnv,
) -> Result<ScanRun, ScanError> {
    let kind = plan.kind.clone();
    let dev = |error| ScanError::Device {
        kind: kind.clone(),
        error,
    };
    let refuse = |m: String| ScanError::Refused(m);
    let start: Pos = inst.stage.target().map_err(dev)?;
    let travel = inst.stage.travel_range().map_err(dev)?;
    let limits = env
        .limits
        .within_travel(travel)
        .map_err(|e| refuse(e.message))?;
    limits.preflight(plan, start).map_err(|e| refuse(e.0))?;
    let Some(timing) = inst.stage.line_timing().map_err(dev)? else {
        return Err(refuse(format!(
            "{kind}: mode \"raster\" needs a stage with a wave generator and a data recorder; {} has none (use the default mode \"points\")",
            inst.stage.name()
        )));
    };
    if opts.samples_per_pixel < 1 {
        return Err(refuse(format!(
            "{kind}: samples_per_pixel = {}: must be ≥ 1",
            opts.samples_per_pixel
        )));
    }
    let rp = plan_lines(plan, start, &timing, inst.settle_s, &limits).map_err(refuse)?;
    let (rows, cols) = (plan.rows(), plan.cols());
    let move_s = inst.stage.move_time_s();
    let per_line = move_s + rp.line_s + inst.qpd.overhead_s();
    let eta = rows as f64 * per_line
        + if plan.return_to_start {
            inst.settle_s
        } else {
            0.0
        };
    let clock_kind = if inst.clock.is_virtual() {
        "simulated"
    } else {
        "real"
    };
    (env.log)(&format!(
        "{} raster: {rows} lines of {cols} pixels at {:.4} µm/s ({} per pixel, line {} incl. turnaround {}), ETA {} ({clock_kind} time)",
        plan.describe(),
        rp.speed_um_s,
        fmt_seconds(plan.dwell_s),
        fmt_seconds(rp.line_s),
        fmt_seconds(rp.turnaround_s),
        fmt_seconds(eta)
    ));
    let (xn, yn) = (plan.fast.axis.name(), plan.row_axis().name());
    if let Some(o) = env.observer {
        o.started(&ScanStart {
            kind: &kind,
            rows,
            cols,
            x: &rp.cols,
            y: &rp.rows,
            x_name: xn,
            y_name: yn,
            points_total: rows * cols,
            eta_s: eta,
            meta: &env.meta,
        });
    }
    let bar = progress_bar(env, rows, "lines", &kind);
    let mut img = [
        Array2::from_elem((rows, cols), f64::NAN),
        Array2::from_elem((rows, cols), f64::NAN),
        Array2::from_elem((rows, cols), f64::NAN),
    ];
    let mut raw: [Vec<Vec<f64>>; 6] = Default::default();
    let (mut err_max, mut err_ss, mut n_err) = (0.0f64, 0.0, 0usize);
    let (mut spp_min, mut spp_sum) = (usize::MAX, 0usize);
    let mut lag_sum = (0.0, 0usize);
    let mut sample_rate = None;
    let mut sz_measured = true;
    let mut ph = LinePhases::default();
    let clock = ScanClock::start(inst);
    let mut ended = Ended::Complete;
    let mut measured = 0usize;
    let mut stop_note: Option<String> = None;
    let mut revised = false;
    for l in &rp.lines {
        if env.abort.swap(false, Ordering::SeqCst) {
            ended = Ended::Aborted { measured };
            break;
        }
        let t = std::time::Instant::now();
        let armed = arm(inst, &l.sweep, opts, plan.dwell_s);
        ph.configure_s += t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        // no settle here: the wave's speed-up ramp (settle_s) and margin (settle_s at line
        // speed) come before the first pixel, and the pixels are binned by measured position
        let moved = armed.and_then(|()| inst.stage.move_to(l.start));
        ph.move_s += t.elapsed().as_secs_f64();
        let result = moved.and_then(|()| measure_line(inst, l, &rp.cols, env, &mut ph));
        match result {
            Ok(Some(d)) => {
                for (c, b) in d.bins.iter().enumerate() {
                    for (i, &m) in b.mean.iter().enumerate() {
                        img[c][[l.row, i]] = m;
                    }
                }
                for (i, (&p, &n)) in d.bins[0].position.iter().zip(&d.bins[0].count).enumerate() {
                    let e = p - rp.cols[i];
                    err_max = err_max.max(e.abs());
                    err_ss += e * e;
                    n_err += 1;
                    spp_min = spp_min.min(n);
                    spp_sum += n;
                }
                // the lag: target − measured over the line's pixels
                let lo = rp.cols[0].min(rp.cols[cols - 1]);
                let hi = rp.cols[0].max(rp.cols[cols - 1]);
                for (t, x) in d.record.target_um.iter().zip(&d.record.position_um) {
                    if *x >= lo && *x <= hi {
                        lag_sum.0 += (t - x).abs();
                        lag_sum.1 += 1;
                    }
                }
                sample_rate = Some(1.0 / d.trace.dt_s);
                sz_measured &= d.trace.sz_measured;
                raw[0].push(d.trace.sx[..d.positions.len()].to_vec());
                raw[1].push(d.trace.sy[..d.positions.len()].to_vec());
                raw[2].push(d.trace.sz[..d.positions.len()].to_vec());
                raw[3].push(d.positions);
                raw[4].push(d.record.target_um);
                raw[5].push(d.record.position_um);
                if let Some(o) = env.observer {
                    // one line at a time: a raster line is seconds of work at most
                    let row: Vec<_> = (0..cols)
                        .map(|i| (l.row, i, [0, 1, 2].map(|c| img[c][[l.row, i]])))
                        .collect();
                    o.points(&row);
                }
                measured += cols;
                ph.lines += 1;
                bar.inc(1);
                if !revised && !inst.clock.is_virtual() && rows > 1 {
                    revised = true;
                    let per = clock.wall_s();
                    if (per - per_line).abs() > 0.1 * per_line {
                        (env.log)(&format!(
                            "{kind}: the first line took {} (the ETA assumed {}): ETA now {} for the remaining {} lines",
                            fmt_seconds(per),
                            fmt_seconds(per_line),
                            fmt_seconds(per * (rows - 1) as f64),
                            rows - 1
                        ));
                    }
                }
            }
            Ok(None) => {
                // Ctrl-C during the wave: the stage stopped the generator and the axes
                let _ = inst.qpd.stop_buffered();
                stop_note = Some(format!(
                    "the wave generator and the axes were stopped during row {}",
                    l.row + 1
                ));
                ended = Ended::Aborted { measured };
                break;
            }
            Err(error) => {
                // every fault: digitiser stopped, wave generator off, axes stopped
                let q = inst.qpd.stop_buffered().err();
                let st = inst.stage.stop_line(&l.sweep).err();
                stop_note = Some(match (q, st) {
                    (_, Some(e)) => format!("stopping the wave generator and the axes failed too: {e}"),
                    (Some(e), None) => format!("the wave generator and the axes were stopped; stopping the digitiser failed: {e}"),
                    (None, None) => "the wave generator and the axes were stopped".into(),
                });
                ended = Ended::Failed {
                    measured,
                    error,
                    stage_fault: true,
                };
                break;
            }
        }
    }
    bar.finish_and_clear();
    if let Some(n) = &stop_note {
        (env.log)(&format!("{kind}: {n}; no further motion"));
    }
    let mut returned = false;
    let mut return_error = None;
    if plan.return_to_start && ended == Ended::Complete {
        match inst.move_settle(start) {
            Ok(()) => returned = true,
            Err(e) => {
                (env.log)(&format!(
                    "{kind}: could NOT return to the start position: {e}"
                ));
                let _ = inst.stage.stop();
                return_error = Some(e.to_string());
            }
        }
    }
    let status = ended.status();
    let n_lines = ph.lines.max(1) as f64;
    let ms = |s: f64| s / n_lines * 1e3;
    let first = &rp.lines[0].sweep;
    let mut meta = json!({
        "plan": plan,
        "mode": "raster",
        "status": status,
        "points_total": rows * cols,
        "points_measured": measured,
        "lines_measured": ph.lines,
        "start_position_um": start,
        "returned_to_start": returned,
        "stop": stop_note,
        "limits": limits,
        "instrument": inst.description,
        "raster": {
            "line_speed_um_s": rp.speed_um_s,
            "dwell_s": plan.dwell_s,
            "line_s": rp.line_s,
            "turnaround_s": rp.turnaround_s,
            "servo_cycle_s": timing.servo_cycle_s,
            "wave_points": first.points,
            "wave_rate": first.rate,
            "speedupdown_points": first.speedupdown,
            "record_rate": first.record_rate,
            "record_sample_s": f64::from(first.record_rate) * timing.servo_cycle_s,
            "trigger_line": timing.trigger_line,
            "sample_rate_hz": sample_rate,
            "samples_per_pixel_asked": opts.samples_per_pixel,
            "samples_per_pixel_min": (spp_min != usize::MAX).then_some(spp_min),
            "samples_per_pixel_mean": (n_err > 0).then(|| spp_sum as f64 / n_err as f64),
            "position_error_um_max": (n_err > 0).then_some(err_max),
            "position_error_um_rms": (n_err > 0).then(|| (err_ss / n_err as f64).sqrt()),
            "lag_um_mean": (lag_sum.1 > 0).then(|| lag_sum.0 / lag_sum.1 as f64),
            "sz_measured": sz_measured,
            "binning": "each pixel: the digitiser samples whose measured stage position (recorder, interpolated) lies within half a pitch of its centre; its value is their least-squares line (value against position) at the centre",
        },
        "time": clock.json(inst, eta),
    });
    meta["time"]["lines"] = json!({
                "move_ms": ms(ph.move_s),
                "configure_arm_ms": ms(ph.configure_s),
                "wave_ms": ms(ph.wave_s),
                "qpd_read_ms": ms(ph.qpd_s),
        "record_read_ms": ms(ph.record_s),
    });
    if let Ended::Failed { error, .. } = &ended {
        meta["error"] = json!({ "message": error.to_string(), "stage_fault": true });
    }
    if let Some(e) = return_error {
        meta["return_error"] = json!(e);
    }
    let mk =
        |d: Array2<f64>| Image::new(d, rp.cols.clone(), rp.rows.clone()).with_axis_names(xn, yn);
    let [sx, sy, mut sz] = img;
    if !sz_measured {
        sz.fill(f64::NAN);
    }
    let names = [
        "sx",
        "sy",
        "sz",
        "position_um",
        "record_target_um",
        "record_position_um",
    ];
    let scan = Scan {
        sx: mk(sx),
        sy: mk(sy),
        sz: mk(sz),
        status,
        meta,
        raw: names
            .iter()
            .zip(&raw)
            .map(|(n, v)| (n.to_string(), padded(v, rows)))
            .collect(),
    };
    Ok(finish(inst, env, &kind, scan, ended, returned))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A stage sweeping 0 → 6.3 µm at 1 µm/ms under a first-order lag τ: the signal is a
    /// function of the *true* position. Binning by the measured position recovers the
    /// profile; binning by the commanded position is off by about v·τ.
    #[test]
    fn binning_by_measured_position_removes_the_lag() {
        let (v, tau, dt) = (1000.0, 0.5e-3, 1e-6); // µm/s, s, s
        let n_pix = 64;
        let (from, to) = (0.0, 6.3);
        let f = |x: f64| (x * 1.3).sin(); // the scene along the line
        let t_end = 7.8e-3;
        let steps = (t_end / dt) as usize;
        let (mut cmd, mut x) = (Vec::new(), Vec::new());
        let mut p = -0.5; // start at rest before the line
        for k in 0..steps {
            let c = -0.5 + v * (k as f64 * dt);
            p += (1.0 - (-dt / tau).exp()) * (c - p);
            cmd.push(c);
            x.push(p);
        }
        let values: Vec<f64> = x.iter().map(|&p| f(p)).collect();
        let good = bin_line(&x, &values, from, to, n_pix).unwrap();
        let by_cmd = bin_line(&cmd, &values, from, to, n_pix).unwrap();
        let w = (to - from) / (n_pix - 1) as f64;
        for i in 0..n_pix {
            let c = from + i as f64 * w;
            // the mean of f over a pixel differs from f(c) by ≤ f''·w²/24 ≈ 1.69·0.01/24
            assert!((good.mean[i] - f(c)).abs() < 1e-3, "{i}");
            // the samples' mean position is the centre to within one sample spacing v·dt
            assert!(
                (good.position[i] - c).abs() <= v * dt,
                "{i}: {}",
                good.position[i]
            );
        }
        // by the command, the profile is shifted by v·τ = 0.5 µm: far off somewhere
        let worst = (0..n_pix)
            .map(|i| (by_cmd.mean[i] - f(from + i as f64 * w)).abs())
            .fold(0.0, f64::max);
        assert!(worst > 0.4, "{worst}");
    }

    #[test]
    fn positions_interpolate_the_record_and_refuse_samples_after_it() {
        let rec = [0.0, 1.0, 4.0];
        let p = positions_at_samples(&rec, 1e-3, 5, 0.5e-3, 0.0).unwrap();
        assert_eq!(p, vec![0.0, 0.5, 1.0, 2.5, 4.0]);
        let e = positions_at_samples(&rec, 1e-3, 6, 0.5e-3, 0.0).unwrap_err();
        assert!(e.contains("sample 5") && e.contains("0.002000 s"), "{e}");
        assert!(positions_at_samples(&rec, 0.0, 1, 1.0, 0.0)
            .unwrap_err()
            .contains("record_dt = 0"));
    }

    /// Samples that fall off-centre in every pixel the same way (a one-way raster's digitiser
    /// phase): on a linear signal the pixel value is the signal at the centre exactly, where
    /// the plain mean would be off by slope × the offset.
    #[test]
    fn pixel_values_are_moved_to_the_pixel_centre() {
        let f = |x: f64| 0.3 + 2.0 * x;
        // pixels 0.1 wide centred on 0, 0.1, …, 0.5; 4 samples each at −0.05, −0.025, 0, 0.025
        let x: Vec<f64> = (0..24).map(|k| -0.05 + 0.025 * k as f64).collect();
        let v: Vec<f64> = x.iter().map(|&p| f(p)).collect();
        let b = bin_line(&x, &v, 0.0, 0.5, 6).unwrap();
        for i in 0..6 {
            let c = 0.1 * i as f64;
            assert_eq!(b.count[i], 4);
            assert!((b.position[i] - (c - 0.0125)).abs() < 1e-12);
            assert!(
                (b.mean[i] - f(c)).abs() < 1e-12,
                "{i}: {} vs {}",
                b.mean[i],
                f(c)
            );
        }
        // one sample, or all at one position: their mean
        let b = bin_line(&[0.0, 1.0, 1.0], &[5.0, 1.0, 3.0], 0.0, 1.0, 2).unwrap();
        assert_eq!(b.mean, vec![5.0, 2.0]);
    }

    #[test]
    fn an_empty_pixel_is_named() {
        let x = [0.0, 0.1, 0.9, 1.0];
        let e = bin_line(&x, &[1.0; 4], 0.0, 1.0, 3).unwrap_err();
        assert!(
            e.starts_with("pixel 1 (centre 0.5000 µm) got no sample"),
            "{e}"
        );
        assert!(bin_line(&x, &[1.0; 3], 0.0, 1.0, 3).is_err());
    }
}
