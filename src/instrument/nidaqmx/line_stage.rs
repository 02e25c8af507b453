//! The NI raster plugged into the existing raster engine (`acquire::raster::run_raster`) through
//! the `Stage` line interface: a Nano-Drive whose x and y external inputs are driven by the NI
//! board's outputs (`[raster]`). Point moves, positions, travel and stop are the Nano-Drive's
//! (Madlib); a hardware-timed line is the board's:
//!
//! - `line_timing`: the board's sample clock (`qpd.rate_hz`) is the "servo cycle": one AO sample
//!   and one AI sample of every input per tick;
//! - `configure_line`: the line's targets per tick → volts (checked against the inputs' 0–10 V
//!   before any task exists), y held at the line's y; AO and AI tasks configured
//!   ([`NiRaster::configure`]);
//! - `start_line`: AI (waiting for the AO start trigger), then AO;
//! - `wait_line`: the AI stream read in chunks while the stage sweeps; Ctrl-C between chunks
//!   stops both tasks and holds the outputs at the present position;
//! - `read_line_record`: the targets and the sensor monitor's positions, sample for sample; the
//!   QPD's samples go to the [`NiQpd`](super::NiQpd) through a shared slot, read by the engine
//!   with `Qpd::read_buffered`;
//! - `stop_line`: tasks stopped and cleared, outputs held at the present position, the
//!   Nano-Drive held.
//!
//! The Nano-Drive is assumed to follow whichever of its inputs changed last (external input or
//! USB command; docs/hardware.md §12): the outputs are only ever written with the position the
//! stage is at or the line's own waveform, which starts where the engine moved the stage.

use super::raster::{waveform_volts, NiRaster, CHUNK};
use crate::instrument::line::{LineSweep, LineTiming, SweepRecord};
use crate::instrument::madlib::MadlibStage;
use crate::instrument::{BufferedTrace, DeviceError, Pos, Stage};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

/// Where a line's QPD samples wait for `Qpd::read_buffered`.
pub type LineSlot = Arc<Mutex<Option<BufferedTrace>>>;

/// A Nano-Drive with NI-driven external inputs.
pub struct NiLineStage {
    stage: MadlibStage,
    raster: NiRaster,
    slot: LineSlot,
    targets: Vec<f64>,
    x_volts: Vec<f64>,
    record: Option<SweepRecord>,
}

impl NiLineStage {
    pub fn new(stage: MadlibStage, raster: NiRaster, slot: LineSlot) -> NiLineStage {
        NiLineStage {
            stage,
            raster,
            slot,
            targets: Vec::new(),
            x_volts: Vec::new(),
            record: None,
        }
    }

    pub fn madlib(&self) -> &MadlibStage {
        &self.stage
    }

    fn rate(&self) -> f64 {
        self.raster.options().qpd.rate_hz
    }

    fn err(&self, detail: String) -> DeviceError {
        DeviceError::Other {
            device: format!(
                "{} + NI {}",
                self.stage.name(),
                self.raster.options().qpd.device
            ),
            detail,
        }
    }

    /// Tasks stopped and cleared, outputs held at the position the Nano-Drive reads (the
    /// commanded target when it cannot be read).
    fn hold_here(&mut self) -> Result<(), DeviceError> {
        let p = match self.stage.position() {
            Ok(p) => p,
            Err(e) => {
                self.raster.clear();
                return Err(e);
            }
        };
        self.raster.hold([p[0], p[1]])
    }
}

impl Stage for NiLineStage {
    fn name(&self) -> String {
        self.stage.name()
    }
    fn position(&mut self) -> Result<Pos, DeviceError> {
        self.stage.position()
    }
    fn target(&mut self) -> Result<Pos, DeviceError> {
        self.stage.target()
    }
    fn move_to(&mut self, target: Pos) -> Result<(), DeviceError> {
        self.stage.move_to(target)
    }
    fn move_to_or_abort(&mut self, target: Pos, abort: &AtomicBool) -> Result<bool, DeviceError> {
        self.stage.move_to_or_abort(target, abort)
    }
    fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError> {
        self.stage.travel_range()
    }
    fn stop(&mut self) -> Result<(), DeviceError> {
        self.stage.stop()
    }
    fn move_time_s(&self) -> f64 {
        self.stage.move_time_s()
    }

    fn line_timing(&mut self) -> Result<Option<LineTiming>, DeviceError> {
        Ok(Some(LineTiming {
            servo_cycle_s: 1.0 / self.rate(),
            // the board streams from host memory: a line is limited by memory, not a table
            max_wave_points: 1 << 24,
            max_record_points: 1 << 24,
            trigger_line: None,
        }))
    }

    fn configure_line(&mut self, s: &LineSweep) -> Result<(), DeviceError> {
        if s.axis != 0 {
            return Err(self.err(format!(
                "configure_line: the NI raster sweeps x (raster.ao.x); this line sweeps {}",
                crate::instrument::AXES[s.axis.min(2)]
            )));
        }
        self.record = None;
        let targets = s.targets_per_cycle();
        let o = self.raster.options().clone();
        // pre-flight: the whole waveform within the external input's range
        self.x_volts =
            waveform_volts(&targets, o.volts_per_um[0], "raster x").map_err(|m| self.err(m))?;
        self.targets = targets;
        Ok(())
    }

    /// The tasks are made for every line (the engine configures a repeated line once, and
    /// the slow axis's voltage is the line's own): AO x the waveform, AO y the row's position.
    fn start_line(&mut self, _s: &LineSweep) -> Result<(), DeviceError> {
        if let Ok(mut g) = self.slot.lock() {
            *g = None;
        }
        if self.x_volts.is_empty() {
            return Err(self.err("start_line: no line configured".into()));
        }
        let o = self.raster.options().clone();
        let mut volts = vec![self.x_volts.clone()];
        if !o.ao[1].is_empty() {
            let y = self.stage.target()?[1];
            let yv =
                waveform_volts(&[y], o.volts_per_um[1], "raster y").map_err(|m| self.err(m))?[0];
            volts.push(vec![yv; self.x_volts.len()]);
        }
        self.raster.configure(&volts)?;
        self.raster.start()
    }

    fn wait_line(&mut self, _s: &LineSweep, abort: &AtomicBool) -> Result<bool, DeviceError> {
        let o = self.raster.options().clone();
        let n = self.targets.len();
        let chans = o.qpd.inputs.names().len();
        let mut inputs: Vec<Vec<f64>> = vec![Vec::with_capacity(n); chans];
        let mut pos_v = Vec::with_capacity(n);
        // a chunk's time plus a margin for the first (the task's start)
        let timeout = CHUNK as f64 / o.qpd.rate_hz + o.qpd.timeout_margin.as_secs_f64();
        while pos_v.len() < n {
            if abort.load(Ordering::SeqCst) {
                self.hold_here()?;
                return Ok(false);
            }
            let c = self.raster.read_chunk(timeout)?;
            if c.position_v.is_empty() {
                break;
            }
            for (k, v) in c.inputs.into_iter().enumerate() {
                inputs[k].extend(v);
            }
            pos_v.extend(c.position_v);
        }
        self.hold_here()?;
        let m = pos_v.len();
        // the QPD's samples, volts → signals as a point read does
        let flat: Vec<f64> = inputs.iter().flatten().copied().collect();
        let (mut sx, mut sy, mut sz) = (
            Vec::with_capacity(m),
            Vec::with_capacity(m),
            Vec::with_capacity(m),
        );
        for i in 0..m {
            let v = o.qpd.inputs.signals(&flat, m, i);
            let r = o.qpd.calibration.apply(v, [0.0; 3], 1);
            sx.push(r.sx);
            sy.push(r.sy);
            sz.push(r.sz);
        }
        let dt = 1.0 / o.qpd.rate_hz;
        if let Ok(mut g) = self.slot.lock() {
            *g = Some(BufferedTrace {
                t0_s: 0.0,
                dt_s: dt,
                sx,
                sy,
                sz,
                sz_measured: true,
            });
        }
        self.record = Some(SweepRecord {
            sample_time_s: dt,
            target_um: self.targets[..m].to_vec(),
            position_um: pos_v.iter().map(|v| v / o.position_volts_per_um).collect(),
        });
        Ok(true)
    }

    fn read_line_record(&mut self, _s: &LineSweep) -> Result<SweepRecord, DeviceError> {
        self.record
            .take()
            .ok_or_else(|| self.err("read_line_record: no line was recorded".into()))
    }

    fn stop_line(&mut self, _s: &LineSweep) -> Result<(), DeviceError> {
        let a = self.hold_here();
        let b = self.stage.stop();
        a.and(b)
    }
}
