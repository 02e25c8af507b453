//! Point by point: at every pixel move the stage, wait the settle time, average the QPD over
//! the dwell. A step is one point; the engine pauses between points.
//!
//! Pre-flight beyond the engine's: the speed between consecutive points, distance divided by
//! (settle + dwell), against `[safety] max_speed_um_s`. ETA per point: settle and dwell, and
//! on hardware the mean move time and the QPD's time beyond its samples measured so far (link
//! included). On a real-time instrument the metadata has `time.phases`: milliseconds per
//! point spent moving, settling and reading the QPD, and per command what the links carried.

use super::{samples_per_point, Checked, Layout, StepFault, StepResult, StopCause, Strategy};
use crate::acquire::error::ScanError;
use crate::acquire::plan::{fmt_seconds, Point};
use crate::instrument::link::LinkCosts;
use crate::instrument::{DeviceError, Instrument, Pos};
use serde_json::{json, Value};

/// Point by point (`mode: "points"`, the default).
#[derive(Default)]
pub struct PointStrategy {
    points: Vec<Point>,
    n_samples: usize,
    dwell_s: f64,
    speed_um_s: f64,
    at: Option<Pos>,
    phases: Phases,
    /// The last point's samples at the rail, until the engine takes them.
    clipped: Vec<crate::acquire::clip::ClippedPixel>,
}

impl PointStrategy {
    pub fn new() -> PointStrategy {
        PointStrategy::default()
    }
}

impl Strategy for PointStrategy {
    fn mode(&self) -> &'static str {
        "points"
    }

    fn prepare(&mut self, inst: &mut Instrument, checked: &Checked) -> Result<Layout, ScanError> {
        let (plan, points) = (checked.plan, checked.points);
        let rate = inst.qpd.sample_rate();
        self.n_samples = samples_per_point(plan.dwell_s, rate);
        self.dwell_s = self.n_samples as f64 / rate;
        self.speed_um_s = checked
            .limits
            .check_speed(&plan.kind, points, inst.settle_s, self.dwell_s)
            .map_err(|e| ScanError::Refused(e.0))?;
        self.points = points.to_vec();
        // the move time per point (the simulator's model; on hardware the device's model of
        // each step where it has one — Madlib: its calls at their measured cost and the
        // stage's measured settling — else the mean of the moves measured so far, link
        // included) and the QPD's measured time beyond its samples
        let move_s = if points.is_empty() {
            0.0
        } else {
            let mut from = checked.start;
            let mut sum = 0.0;
            for p in points {
                sum += inst.stage.move_time_for_s(from, p.target);
                from = p.target;
            }
            sum / points.len() as f64
        };
        let read_extra_s = inst.qpd.overhead_s();
        let eta_detail = format!(
            "{} points, {}settle {} + dwell {}{} per point",
            points.len(),
            if move_s > 0.0 {
                format!("move {} + ", fmt_seconds(move_s))
            } else {
                String::new()
            },
            fmt_seconds(inst.settle_s),
            if self.dwell_s > plan.dwell_s * (1.0 + 1e-6) + 1e-12 {
                // the asked dwell is shorter than the QPD's read: say what will happen
                format!(
                    "{} (asked {}: a read is whole samples, {} at {} S/s)",
                    fmt_seconds(self.dwell_s),
                    fmt_seconds(plan.dwell_s),
                    self.n_samples,
                    rate
                )
            } else {
                fmt_seconds(self.dwell_s)
            },
            if read_extra_s > 0.0 {
                format!(" + QPD link {}", fmt_seconds(read_extra_s))
            } else {
                String::new()
            },
        );
        // the links' costs from here on
        let _ = (inst.stage.link_costs(), inst.qpd.link_costs());
        Ok(Layout {
            steps: points.len(),
            steps_per_row: plan.cols(),
            unit: "point",
            step_s: inst.settle_s + move_s + read_extra_s + self.dwell_s,
            eta_detail,
        })
    }

    fn step(&mut self, inst: &mut Instrument, i: usize) -> StepResult {
        let p = self.points[i];
        let t = std::time::Instant::now();
        let moved = inst.stage.move_to(p.target);
        self.phases.move_s += t.elapsed().as_secs_f64();
        moved.map_err(StepFault::stage)?;
        let t = std::time::Instant::now();
        inst.clock.wait(inst.settle_s);
        self.phases.settle_s += t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        // the scan stores the means only: the device may send less (SCPI: `MEAS:QPD?`)
        let read = inst.qpd.read_for(self.dwell_s);
        self.phases.qpd_s += t.elapsed().as_secs_f64();
        let r = read.map_err(StepFault::other)?;
        self.at = Some(p.target);
        self.phases.points += 1;
        if r.clipped.iter().any(|&k| k > 0) {
            let k = r.clipped.map(|k| u32::try_from(k).unwrap_or(u32::MAX));
            self.clipped.push((p.row, p.col, k));
        }
        Ok(vec![(p.row, p.col, [r.sx, r.sy, r.sz])])
    }

    fn take_clipped(&mut self) -> Vec<crate::acquire::clip::ClippedPixel> {
        std::mem::take(&mut self.clipped)
    }

    fn resting_at(&self) -> Option<Pos> {
        self.at
    }

    /// The stage rests on the last point measured: nothing to stop.
    fn pause(&mut self, _inst: &mut Instrument) -> Result<(), DeviceError> {
        Ok(())
    }

    /// After a stage fault (a controller error mid-move, an on-target timeout: the axis may
    /// still be moving) the stage's stop (PI: `STP`); nothing otherwise (a point's move has
    /// ended before its read).
    fn stop(&mut self, inst: &mut Instrument, cause: StopCause) -> Option<Result<String, String>> {
        (cause == StopCause::Fault { stage: true }).then(|| {
            inst.stage
                .stop()
                .map(|()| format!("stage stopped ({})", inst.stage.name()))
                .map_err(|e| format!("the stop command failed too: {e}"))
        })
    }

    fn metadata(
        &mut self,
        inst: &mut Instrument,
        _steps: usize,
        loop_s: f64,
        log: &dyn Fn(&str),
    ) -> Value {
        let mut m = json!({
            "samples_per_point": self.n_samples,
            "max_speed_between_points_um_s": self.speed_um_s,
        });
        if !inst.clock.is_virtual() && self.phases.points > 0 {
            let ph = &mut self.phases;
            ph.loop_s = loop_s;
            ph.dwell_s = self.dwell_s;
            ph.stage_link = inst.stage.link_costs();
            ph.qpd_link = inst.qpd.link_costs();
            let j = ph.to_json();
            if let Some(line) = phase_summary(&j) {
                log(&line);
            }
            m["time"] = json!({ "phases": j });
        }
        m
    }
}

/// Wall time of a scan's points by phase (real-time instruments), and what the links carried.
#[derive(Default)]
struct Phases {
    points: usize,
    /// The loop over the points (pauses excluded), s.
    loop_s: f64,
    /// `move_to` (PI: `MOV`, `ERR?`, motion polling until on target), s, summed.
    move_s: f64,
    /// The settle wait, s, summed.
    settle_s: f64,
    /// QPD reads (command, acquisition, reply), s, summed.
    qpd_s: f64,
    /// Acquisition time per read, samples / rate, s.
    dwell_s: f64,
    stage_link: LinkCosts,
    qpd_link: LinkCosts,
}

impl Phases {
    /// `meta.time.phases`: milliseconds per point for each phase; per command word the count,
    /// bytes (both ways), write and reply milliseconds per point.
    fn to_json(&self) -> Value {
        let n = self.points.max(1) as f64;
        let ms = |s: f64| s / n * 1e3;
        let link = |costs: &LinkCosts| {
            let mut m = serde_json::Map::new();
            for (w, c) in costs {
                m.insert(
                    w.clone(),
                    json!({
                        "per_point": c.n as f64 / n,
                        "bytes_per_point": (c.bytes_out + c.bytes_in) as f64 / n,
                        "write_ms": ms(c.write_s),
                        "reply_ms": ms(c.reply_s),
                    }),
                );
            }
            Value::Object(m)
        };
        let bytes: u64 = self
            .stage_link
            .iter()
            .chain(&self.qpd_link)
            .map(|(_, c)| c.bytes_out + c.bytes_in)
            .sum();
        let per_point = ms(self.loop_s);
        json!({
            "points": self.points,
            "per_point_ms": per_point,
            "move_ms": ms(self.move_s),
            "settle_ms": ms(self.settle_s),
            "qpd_ms": ms(self.qpd_s),
            "dwell_ms": self.dwell_s * 1e3,
            "qpd_beyond_dwell_ms": ms(self.qpd_s) - self.dwell_s * 1e3,
            "other_ms": per_point - ms(self.move_s + self.settle_s + self.qpd_s),
            "stage_link": link(&self.stage_link),
            "qpd_link": link(&self.qpd_link),
            "link_bytes_per_point": bytes as f64 / n,
        })
    }
}

/// One line for the operator from `meta.time.phases`: where the time per point went.
fn phase_summary(p: &Value) -> Option<String> {
    let f = |k: &str| p[k].as_f64();
    let cmds = |k: &str| -> String {
        p[k].as_object()
            .map(|m| {
                m.iter()
                    .map(|(w, c)| {
                        format!(
                            "{w} {:.2}× {:.2} ms",
                            c["per_point"].as_f64().unwrap_or(0.0),
                            c["write_ms"].as_f64().unwrap_or(0.0)
                                + c["reply_ms"].as_f64().unwrap_or(0.0)
                        )
                    })
                    .collect::<Vec<_>>()
                    .join(", ")
            })
            .unwrap_or_default()
    };
    Some(format!(
        "{} points, {:.2} ms per point = move {:.2} ms [{}] + settle {:.2} ms + QPD {:.2} ms (dwell {:.2} ms) [{}] + other {:.2} ms; links {:.0} bytes per point",
        p["points"].as_u64()?,
        f("per_point_ms")?,
        f("move_ms")?,
        cmds("stage_link"),
        f("settle_ms")?,
        f("qpd_ms")?,
        f("dwell_ms")?,
        cmds("qpd_link"),
        f("other_ms")?,
        f("link_bytes_per_point")?,
    ))
}
