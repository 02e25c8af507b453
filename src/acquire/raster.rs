//! Hardware-timed raster scans (`scan_xy(#{…, mode: "raster"})`): the planning of the lines
//! and the binning of their samples. The fast axis sweeps each line at constant speed under
//! the controller's clock (a wave generator), the controller's trigger output starts the
//! digitiser, the data recorder gives the measured position of the stage, and each line's
//! digitiser samples are binned into pixels by that *measured* position (docs/hardware.md
//! §10). The acquisition of a line is `strategy::line`; the engine's loop (pre-flight, ETA,
//! pause, abort, return to start, autosave) is the one of every scan (`engine::run`).
//!
//! - [`plan_lines`]: every line's wave (ramps and margins included) checked against the soft
//!   limits, and the line speed (pitch / dwell) against the speed limit, before the first move;
//! - [`positions_at_samples`], [`bin_line`]: the stage position at each digitiser sample, and
//!   the pixels binned by it (any buffered acquisition, also a DAQ board's stream).
//!
//! Conventions: positions in µm, times in s. A line of `n` pixels from `from` to `to` has its
//! pixel centres at `from + i·w`, `w = (to − from)/(n − 1)` (as the point-by-point scans), and
//! pixel `i` takes the samples whose measured position lies within `w/2` of its centre
//! (half-open: `[c − w/2, c + w/2)` in the sweep direction).

use super::limits::SoftLimits;
use super::plan::Plan;
use crate::instrument::line::{LineSweep, LineTiming};
use crate::instrument::Pos;

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
        let c = from + i as f64 * w;
        // what the samples did there: consecutive samples on either side of the pixel (the
        // line too fast for the digitiser), or none valid there at all
        let lo = c - 0.5 * w.abs();
        let hi = c + 0.5 * w.abs();
        let jump = positions
            .windows(2)
            .enumerate()
            .find(|(_, p)| (p[0] < lo && p[1] >= hi) || (p[1] < lo && p[0] >= hi));
        let why = match jump {
            Some((k, p)) => format!(
                "the measured position jumps from {:.4} to {:.4} µm between samples {k} and {} (a pixel is {:.4} µm): the line is too fast for the digitiser's rate",
                p[0],
                p[1],
                k + 1,
                w.abs()
            ),
            None if positions.iter().any(|&x| x >= lo && x < hi) => {
                "its samples there are not finite (the digitiser returned NaN or infinity)".into()
            }
            None => "no sample's measured position reaches it (the stage did not cover the line)".into(),
        };
        return Err(format!("pixel {i} (centre {c:.4} µm) got no sample: {why}"));
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
            e == "pixel 1 (centre 0.5000 µm) got no sample: the measured position jumps from 0.1000 to 0.9000 µm between samples 1 and 2 (a pixel is 0.5000 µm): the line is too fast for the digitiser's rate",
            "{e}"
        );
        let e = bin_line(&x, &[1.0; 3], 0.0, 1.0, 3).unwrap_err();
        assert_eq!(e, "4 positions for 3 samples");
        // samples there, but not finite; no sample there at all
        let e = bin_line(&[0.0, 0.5, 1.0], &[1.0, f64::NAN, 1.0], 0.0, 1.0, 3).unwrap_err();
        assert!(
            e.ends_with(
                "its samples there are not finite (the digitiser returned NaN or infinity)"
            ),
            "{e}"
        );
        let e = bin_line(&[0.0, 0.1, 0.2], &[1.0; 3], 0.0, 1.0, 3).unwrap_err();
        assert!(
            e.ends_with(
                "no sample's measured position reaches it (the stage did not cover the line)"
            ),
            "{e}"
        );
    }
}
