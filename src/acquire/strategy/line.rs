//! Hardware-timed lines (`mode: "raster"`): the fast axis sweeps each row at constant speed
//! under the controller's clock (a wave generator), the controller's trigger output starts
//! the digitiser, the data recorder gives the measured position of the stage, and each line's
//! digitiser samples are binned into pixels by that *measured* position (`raster::bin_line`,
//! docs/hardware.md §10). A step is one line; the engine pauses between lines.
//!
//! - `prepare`: the whole waveform of every line (ramps and margins included) against the
//!   soft limits and the line speed (pitch / dwell) against the speed limit
//!   (`raster::plan_lines`); the engine has checked every pixel.
//! - `step`: arm the digitiser on the external trigger; move to the wave's first point (no
//!   settle: the wave's speed-up ramp of `settle` s and its margin of `settle` s at line speed
//!   pass before the first pixel); configure the line (once, when lines repeat; again after a
//!   pause); start the wave; wait for it to *finish* (Ctrl-C during a line takes effect after
//!   it); read the digitiser and the recorder; bin.
//! - `pause` and `stop`: the digitiser stopped, the wave generator off and the axes stopped
//!   (PI: `WGO g 0`, `STP`), where the line ended.
//!
//! Fault classes: a failed `move`, `configure`, `start`, `wait` or recorder read is the
//! stage's; a digitiser that fails (arm, trigger, read) or a line that cannot be binned is
//! not, and a relative scan then returns to its start.

use super::{
    line_by_line_steps, padded, planned, BinStats, Checked, Layout, StepFault, StepResult,
    StopCause, Strategy,
};
use crate::acquire::error::ScanError;
use crate::acquire::plan::fmt_seconds;
use crate::acquire::raster::{
    bin_line, positions_at_samples, LineBins, RasterLine, RasterOptions, RasterPlan,
};
use crate::instrument::line::{LineSweep, LineTiming, SweepRecord};
use crate::instrument::{BufferedTrace, DeviceError, Instrument, Pos, Trigger};
use ndarray::Array2;
use serde_json::{json, Value};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

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

/// Hardware-timed lines. See the module documentation.
pub struct LineStrategy {
    opts: RasterOptions,
    dwell_s: f64,
    rp: Option<Arc<RasterPlan>>,
    timing: Option<LineTiming>,
    ph: LinePhases,
    stats: BinStats,
    /// Raw samples per measured line: sx, sy, sz, position, recorder target, recorder position.
    raw: [Vec<Vec<f64>>; 6],
    /// The line being played or last played.
    current: Option<usize>,
    /// The stop commands went out after it (a pause).
    stopped: bool,
    at: Option<Pos>,
    /// The last line's pixels with samples at the rail, until the engine takes them.
    clipped: Vec<crate::acquire::clip::ClippedPixel>,
}

impl LineStrategy {
    pub fn new(opts: RasterOptions) -> LineStrategy {
        LineStrategy {
            opts,
            dwell_s: 0.0,
            rp: None,
            timing: None,
            ph: LinePhases::default(),
            stats: BinStats::default(),
            raw: Default::default(),
            current: None,
            stopped: false,
            at: None,
            clipped: Vec::new(),
        }
    }

    /// Digitiser stopped, wave generator off, axes stopped; the first error returned (both
    /// are sent). The controller is configured again before the next line.
    fn stop_all(&mut self, inst: &mut Instrument) -> Result<(), String> {
        let Some(s) = self
            .current
            .and_then(|i| self.rp.as_ref().map(|rp| rp.lines[i].sweep.clone()))
        else {
            return Ok(());
        };
        self.ph.configured = None;
        let q = inst.qpd.stop_buffered().err();
        let st = inst.stage.stop_line(&s).err();
        // a stop that failed is sent again at the end of the scan
        self.stopped = st.is_none();
        match (q, st) {
            (_, Some(e)) => Err(format!(
                "stopping the wave generator and the axes failed too: {e}"
            )),
            (Some(e), None) => Err(format!(
                "the wave generator and the axes were stopped; stopping the digitiser failed: {e}"
            )),
            (None, None) => Ok(()),
        }
    }

    /// Measure one line (armed, the stage at rest on its first point).
    fn measure_line(
        &mut self,
        inst: &mut Instrument,
        l: &RasterLine,
        cols: &[f64],
    ) -> Result<LineData, StepFault> {
        let s = &l.sweep;
        let ph = &mut self.ph;
        let t = std::time::Instant::now();
        // the same wave as the last line's (one-way rasters: the slow axis is set by the move
        // to the line's start): the controller keeps it, the recorder restarts with the
        // generator
        if ph.configured.as_ref() != Some(s) {
            ph.configured = None;
            inst.stage
                .lines_for("configure_line")
                .and_then(|l| l.configure_line(s))
                .map_err(StepFault::stage)?;
            ph.configured = Some(s.clone());
        }
        ph.configure_s += t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        inst.stage
            .lines_for("start_line")
            .and_then(|l| l.start_line(s))
            .map_err(StepFault::stage)?;
        // the line is played to its end: Ctrl-C takes effect between lines
        let played = inst
            .stage
            .lines_for("wait_line")
            .and_then(|l| l.wait_line(s, &AtomicBool::new(false)))
            .map_err(StepFault::stage)?;
        ph.wave_s += t.elapsed().as_secs_f64();
        if !played {
            return Err(StepFault::stage(DeviceError::Other {
                device: inst.stage.name(),
                detail: format!("row {}: the line was stopped before its end", l.row + 1),
            }));
        }
        let t = std::time::Instant::now();
        let timeout = std::time::Duration::from_secs_f64(s.duration_s() + 2.0);
        let trace = inst.qpd.read_buffered(timeout).map_err(StepFault::other)?;
        ph.qpd_s += t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        let record = inst
            .stage
            .lines_for("read_line_record")
            .and_then(|l| l.read_line_record(s))
            .map_err(StepFault::stage)?;
        ph.record_s += t.elapsed().as_secs_f64();
        let device = format!("{} + {}", inst.qpd.name(), inst.stage.name());
        let bad = |detail: String| {
            StepFault::other(DeviceError::Other {
                device: device.clone(),
                detail: format!("row {}: {detail}", l.row + 1),
            })
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
        .map_err(bad)?;
        let (c0, c1) = (cols[0], cols[cols.len() - 1]);
        let bin = |v: &[f64]| bin_line(&positions, &v[..keep], c0, c1, cols.len()).map_err(bad);
        let bins = [bin(&trace.sx)?, bin(&trace.sy)?, bin(&trace.sz)?];
        Ok(LineData {
            bins,
            trace,
            positions,
            record,
        })
    }
}

/// One line measured: the binned row and what was binned.
struct LineData {
    bins: [LineBins; 3],
    trace: BufferedTrace,
    positions: Vec<f64>,
    record: SweepRecord,
}

impl Strategy for LineStrategy {
    fn mode(&self) -> &'static str {
        "raster"
    }

    fn prepare(&mut self, inst: &mut Instrument, checked: &Checked) -> Result<Layout, ScanError> {
        let plan = checked.plan;
        let kind = &plan.kind;
        let timing = inst
            .stage
            .line_timing()
            .map_err(|error| ScanError::Device {
                kind: kind.clone(),
                error,
            })?
            .ok_or_else(|| {
                ScanError::Refused(format!(
                    "{kind}: mode \"raster\" needs a stage with a wave generator and a data recorder; {} has none (use the default mode \"points\")",
                    inst.stage.name()
                ))
            })?;
        if self.opts.samples_per_pixel < 1 {
            return Err(ScanError::Refused(format!(
                "{kind}: samples_per_pixel = {}: must be ≥ 1",
                self.opts.samples_per_pixel
            )));
        }
        let rp = checked.raster_lines(&timing, inst.settle_s)?;
        // per line: the move to its start, the wave, and what the devices cost around it (the
        // controller's start, end and recorder readout; the digitiser's arming and read-out)
        let line_extra_s = rp
            .lines
            .first()
            .zip(inst.stage.lines())
            .map_or(0.0, |(l, scan)| scan.line_overhead_s(&l.sweep));
        let move_s = inst.stage.move_time_s();
        let read_s = inst.qpd.overhead_s();
        let step_s = move_s + rp.line_s + line_extra_s + read_s;
        let eta_detail = format!(
            "{} lines of {} pixels at {:.4} µm/s ({} per pixel, line {} incl. turnaround {}; per line also move {} + controller link {} + digitiser {})",
            rp.lines.len(),
            rp.cols.len(),
            rp.speed_um_s,
            fmt_seconds(plan.dwell_s),
            fmt_seconds(rp.line_s),
            fmt_seconds(rp.turnaround_s),
            fmt_seconds(move_s),
            fmt_seconds(line_extra_s),
            fmt_seconds(read_s),
        );
        self.dwell_s = plan.dwell_s;
        self.timing = Some(timing);
        let steps = rp.lines.len();
        self.rp = Some(Arc::new(rp));
        Ok(Layout {
            steps,
            steps_per_row: 1,
            unit: "line",
            step_s,
            eta_detail,
        })
    }

    line_by_line_steps!();

    fn pause(&mut self, inst: &mut Instrument) -> Result<(), DeviceError> {
        self.stop_all(inst).map_err(|detail| DeviceError::Other {
            device: inst.stage.name(),
            detail: format!("pausing: {detail}"),
        })
    }

    fn stop(&mut self, inst: &mut Instrument, _cause: StopCause) -> Option<Result<String, String>> {
        let row = self.current? + 1;
        if self.stopped {
            return Some(Ok(format!(
                "the wave generator and the axes were stopped at the pause after row {row}"
            )));
        }
        Some(
            self.stop_all(inst)
                .map(|()| format!("the wave generator and the axes were stopped after row {row}")),
        )
    }

    fn metadata(
        &mut self,
        _inst: &mut Instrument,
        _steps: usize,
        _loop_s: f64,
        _log: &dyn Fn(&str),
    ) -> Value {
        let (Some(rp), Some(timing)) = (self.rp.as_ref(), self.timing.as_ref()) else {
            return json!({});
        };
        let st = &self.stats;
        let ph = &self.ph;
        let n_lines = ph.lines.max(1) as f64;
        let ms = |s: f64| s / n_lines * 1e3;
        let first = &rp.lines[0].sweep;
        let mut m = json!({
            "lines_measured": ph.lines,
            "raster": {
                "line_speed_um_s": rp.speed_um_s,
                "dwell_s": self.dwell_s,
                "line_s": rp.line_s,
                "turnaround_s": rp.turnaround_s,
                "servo_cycle_s": timing.servo_cycle_s,
                "wave_points": first.points,
                "wave_rate": first.rate,
                "speedupdown_points": first.speedupdown,
                "record_rate": first.record_rate,
                "record_sample_s": f64::from(first.record_rate) * timing.servo_cycle_s,
                "trigger_line": timing.trigger_line,
                "samples_per_pixel_asked": self.opts.samples_per_pixel,
                "binning": "each pixel: the digitiser samples whose measured stage position (recorder, interpolated) lies within half a pitch of its centre; its value is their least-squares line (value against position) at the centre",
            },
            "time": {
                "lines": {
                    "move_ms": ms(ph.move_s),
                    "configure_arm_ms": ms(ph.configure_s),
                    "wave_ms": ms(ph.wave_s),
                    "qpd_read_ms": ms(ph.qpd_s),
                    "record_read_ms": ms(ph.record_s),
                }
            },
        });
        st.merge_into(&mut m["raster"]);
        m
    }

    fn raw(&mut self) -> Vec<(String, Array2<f64>)> {
        let rows = self.rp.as_ref().map_or(0, |rp| rp.lines.len());
        let names = [
            "sx",
            "sy",
            "sz",
            "position_um",
            "record_target_um",
            "record_position_um",
        ];
        names
            .iter()
            .zip(&self.raw)
            .map(|(n, v)| (n.to_string(), padded(v, rows)))
            .collect()
    }

    fn sz_measured(&self) -> bool {
        self.stats.sz_measured
    }
}

impl LineStrategy {
    fn line_step(&mut self, inst: &mut Instrument, rp: &RasterPlan, i: usize) -> StepResult {
        let l = &rp.lines[i];
        self.current = Some(i);
        self.stopped = false;
        let t = std::time::Instant::now();
        arm(inst, &l.sweep, &self.opts, self.dwell_s).map_err(StepFault::other)?;
        self.ph.configure_s += t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        // no settle here: the wave's speed-up ramp (settle_s) and margin (settle_s at line
        // speed) come before the first pixel, and the pixels are binned by measured position
        let moved = inst.stage.move_to(l.start);
        self.ph.move_s += t.elapsed().as_secs_f64();
        moved.map_err(StepFault::stage)?;
        let d = self.measure_line(inst, l, &rp.cols)?;
        let mut end = l.start;
        end[l.sweep.axis] = l.sweep.to_um;
        self.at = Some(end);
        let cols = rp.cols.len();
        let st = &mut self.stats;
        st.add_line(&d.bins[0], &rp.cols);
        st.add_lag(&d.record.target_um, &d.record.position_um, &rp.cols);
        st.sample_rate = Some(1.0 / d.trace.dt_s);
        st.sz_measured &= d.trace.sz_measured;
        let k = d.positions.len();
        if !d.trace.clipped.is_empty() {
            let (c0, c1) = (rp.cols[0], rp.cols[cols - 1]);
            let flags = &d.trace.clipped[..k.min(d.trace.clipped.len())];
            let counts = crate::acquire::clip::line_counts(&d.positions, flags, c0, c1, cols);
            self.clipped = crate::acquire::clip::line_pixels(l.row, &counts);
        }
        self.raw[0].push(d.trace.sx[..k].to_vec());
        self.raw[1].push(d.trace.sy[..k].to_vec());
        self.raw[2].push(d.trace.sz[..k].to_vec());
        self.raw[3].push(d.positions);
        self.raw[4].push(d.record.target_um);
        self.raw[5].push(d.record.position_um);
        self.ph.lines += 1;
        Ok((0..cols)
            .map(|c| (l.row, c, [0, 1, 2].map(|ch| d.bins[ch].mean[c])))
            .collect())
    }
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
