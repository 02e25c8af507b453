//! A Nano-Drive whose x and y external inputs are driven by the NI board's outputs
//! (`[raster] backend = "nidaqmx"`): point moves, positions, travel and stop are the
//! Nano-Drive's (Madlib); a raster frame is the board's, streamed on its clock
//! ([`FrameStream`]): the frame's waveform in volts on ao x/y, written ahead in blocks, and
//! the QPD inputs with the x sensor monitor on the AO sample clock, read in chunks.
//!
//! How the controller combines its external inputs with the USB command is configured
//! (`[raster] external_input`, docs/hardware.md §12):
//!
//! - `"sum"` (MCL's documented behaviour, the default): the position is USB command +
//!   external input. Before a stream the USB command of x and y is handed over to the outputs
//!   ([`HAND_STEP_UM`] at a time: the USB command down, the output up by as much, so that the
//!   stage does not move) until the USB command is 0 and the outputs alone say where the
//!   stage is; the outputs then play target − USB command (= the target). After the stream
//!   (end of frame, pause, fault, Ctrl-C) the outputs hold the present position and are
//!   handed back to USB the same way: the USB command ends at the position, the outputs at
//!   0 V, and `mv` works as before.
//! - `"replace"`: the controller follows the external input alone while it is driven; the
//!   outputs play the target and hold the present position.
//!
//! Every hand-over step is checked against the readings: a stage that moves by more than
//! [`GUARD_UM`] while the position should stand still is stopped at once, with a message
//! naming `external_input` (a `"replace"` controller configured as `"sum"`). The reverse
//! mistake shows in the stream's first milliseconds (the scan engine's guard compares the
//! sensor monitor with the plan) and [`FrameStream::ran_away`] makes the hold undo it.

use super::raster::{waveform_volts, ExternalInput, NiRaster};
use crate::instrument::madlib::MadlibStage;
use crate::instrument::stream::{FrameStream, StreamChunk};
use crate::instrument::{DeviceError, Pos, Stage};
use delegate::delegate;
use std::sync::atomic::AtomicBool;

/// Largest change of the USB command (and of the outputs) in one hand-over step, µm.
pub const HAND_STEP_UM: f64 = 0.5;
/// A reading this far from where the stage should stand during a hand-over is a stage that
/// runs away, µm.
pub const GUARD_UM: f64 = 1.0;
/// A stage still moving when it was held is at rest when it reads this close to where it was
/// held, µm.
pub const REST_UM: f64 = 0.005;
/// After the first hand-over step the readings are watched this long, s.
pub const GUARD_WATCH_S: f64 = 0.003;

/// A Nano-Drive with NI-driven external inputs.
pub struct NiStreamStage {
    stage: MadlibStage,
    raster: NiRaster,
    /// What the outputs hold (µm of the x and y external inputs) while they command part of
    /// the position (sum mode, during a stream and until handed back); zero otherwise.
    ext: [f64; 2],
    /// The stage behaved the other way than configured (a guard fired): holds undo it.
    swapped: bool,
    /// The lag the last frame measured (s).
    lag: Option<f64>,
}

impl NiStreamStage {
    pub fn new(stage: MadlibStage, raster: NiRaster) -> NiStreamStage {
        NiStreamStage {
            stage,
            raster,
            ext: [0.0; 2],
            swapped: false,
            lag: None,
        }
    }

    /// The mode the holds use: the configured one, or the other after a guard fired.
    fn mode(&self) -> ExternalInput {
        match (self.raster.options().external_input, self.swapped) {
            (m, false) => m,
            (ExternalInput::Sum, true) => ExternalInput::Replace,
            (ExternalInput::Replace, true) => ExternalInput::Sum,
        }
    }

    /// What the user is told when the stage ran away.
    fn runaway_advice(&self) -> String {
        let now = self.raster.options().external_input.as_str();
        format!(
            "the likely cause is [raster] external_input = \"{now}\": a Nano-Drive that adds its external input to the USB command needs \"sum\", one that follows the external input alone needs \"replace\" (docs/hardware.md §12 says how to check yours safely)"
        )
    }

    /// The USB command of x and y, µm.
    fn usb(&mut self) -> Result<[f64; 2], DeviceError> {
        let t = self.stage.target()?;
        Ok([t[0], t[1]])
    }

    /// Move the USB command of x and y from `u0` to `u1` while the outputs go from `e0` to
    /// `e1` (µm; `u0 + e0 = u1 + e1`, sum mode), in steps of at most [`HAND_STEP_UM`], each
    /// step's readings checked against the position `p` that should not change.
    fn hand_over(
        &mut self,
        u0: [f64; 2],
        e0: [f64; 2],
        u1: [f64; 2],
        p: [f64; 2],
        what: &str,
    ) -> Result<(), DeviceError> {
        let d = [u1[0] - u0[0], u1[1] - u0[1]];
        let steps = (d[0].abs().max(d[1].abs()) / HAND_STEP_UM).ceil() as usize;
        let s = self.raster.options().volts_per_um;
        let t0 = std::time::Instant::now();
        for i in 1..=steps {
            let f = i as f64 / steps as f64;
            let u = [u0[0] + d[0] * f, u0[1] + d[1] * f];
            let e = [e0[0] - d[0] * f, e0[1] - d[1] * f];
            // the USB command first when it goes down (the position dips by a step at most),
            // the outputs first when they go down
            let usb_first = d[0] <= 0.0 && d[1] <= 0.0;
            if !usb_first {
                self.raster.hold_volts([e[0] * s[0], e[1] * s[1]])?;
                self.ext = e;
            }
            for (k, &v) in u.iter().enumerate() {
                self.stage.command_now(k, v.max(0.0))?;
            }
            if usb_first {
                self.raster.hold_volts([e[0] * s[0], e[1] * s[1]])?;
                self.ext = e;
            }
            // the readings stay where the stage stands; after the first step they are
            // watched for a few ms (a controller that does not sum runs away at once)
            let watch = if i == 1 { GUARD_WATCH_S } else { 0.0 };
            let w0 = std::time::Instant::now();
            loop {
                for k in 0..2 {
                    let r = self.stage.read_now(k)?;
                    if (r - p[k]).abs() > GUARD_UM {
                        return Err(self.err(format!(
                            "the stage ran away while {what} (step {i} of {steps}, {:.1} ms in): {} reads {r:.3} µm, \
                             {:.3} µm from where it stood ({:.3} µm); the hand-over was stopped and the stage held; {}",
                            t0.elapsed().as_secs_f64() * 1e3,
                            crate::instrument::AXES[k],
                            (r - p[k]).abs(),
                            p[k],
                            self.runaway_advice()
                        )));
                    }
                }
                if w0.elapsed().as_secs_f64() >= watch {
                    break;
                }
            }
        }
        Ok(())
    }

    /// Wait (at most 0.1 s) until the x and y readings come within [`REST_UM`] of `q`.
    fn settle(&mut self, q: [f64; 2]) -> Result<(), DeviceError> {
        let t0 = std::time::Instant::now();
        loop {
            let near = (0..2).try_fold(true, |near, k| {
                Ok::<bool, DeviceError>(near && (self.stage.read_now(k)? - q[k]).abs() < REST_UM)
            })?;
            if near || t0.elapsed().as_secs_f64() > 0.1 {
                return Ok(());
            }
            std::thread::sleep(std::time::Duration::from_micros(200));
        }
    }

    /// Sum mode, before a stream: the USB command of x and y handed over to the outputs
    /// until it is 0 (the outputs then hold the position).
    fn take_over(&mut self) -> Result<(), DeviceError> {
        self.swapped = false;
        let u = self.usb()?;
        if u[0] == 0.0 && u[1] == 0.0 {
            return Ok(());
        }
        // where the stage stands: what the outputs add is the reading less the USB command
        // (0 V unless another program left them elsewhere)
        let r = self.stage.position()?;
        let p = [r[0], r[1]];
        let e = if self.ext == [0.0; 2] {
            [(p[0] - u[0]).max(0.0), (p[1] - u[1]).max(0.0)]
        } else {
            self.ext
        };
        let res = self.hand_over(
            u,
            e,
            [0.0; 2],
            p,
            "the outputs took over from the USB command",
        );
        if let Err(e) = res {
            self.swapped = true;
            let _ = self.hold_here();
            return Err(e);
        }
        Ok(())
    }

    /// Stop the stream's tasks and hold the stage where it stands, in the mode in force;
    /// in sum mode the outputs are then handed back to USB. Returns the position.
    fn hold_here(&mut self) -> Result<Pos, DeviceError> {
        // the tasks first: the outputs keep their last sample and the stage comes to rest
        // on it; then the position it reads now is what the outputs hold
        self.raster.clear();
        let p = self.stage.position()?;
        match self.mode() {
            ExternalInput::Replace => {
                self.raster.hold([p[0], p[1]])?;
                if self.swapped {
                    // a controller that follows the last change: the USB command there too
                    for k in 0..2 {
                        self.stage.command_now(k, p[k])?;
                    }
                    self.ext = [0.0; 2];
                }
            }
            ExternalInput::Sum => {
                let u = self.usb()?;
                let e = [(p[0] - u[0]).max(0.0), (p[1] - u[1]).max(0.0)];
                let s = self.raster.options().volts_per_um;
                self.raster.hold_volts([e[0] * s[0], e[1] * s[1]])?;
                self.ext = e;
                let q = [u[0] + e[0], u[1] + e[1]];
                // a stage still moving when it was read comes to rest on `q`
                self.settle(q)?;
                self.hand_over(
                    u,
                    e,
                    q,
                    q,
                    "the outputs were handed back to the USB command",
                )?;
                self.raster.hold_volts([0.0, 0.0])?;
                self.ext = [0.0; 2];
                // each step dipped by a few tens of nm for the time between its two writes
                self.settle(q)?;
            }
        }
        Ok(p)
    }

    pub fn madlib(&self) -> &MadlibStage {
        &self.stage
    }

    fn err(&self, detail: String) -> DeviceError {
        DeviceError::Other {
            device: self.stream_name(),
            detail,
        }
    }

    /// Targets (µm) per output → volts per output (x, then y when wired), refused outside
    /// 0–10 V. In sum mode the outputs play target − USB command.
    fn volts(&mut self, fast: &[f64], slow: &[f64]) -> Result<Vec<Vec<f64>>, DeviceError> {
        let u = match self.raster.options().external_input {
            ExternalInput::Sum => self.usb()?,
            ExternalInput::Replace => [0.0; 2],
        };
        let o = self.raster.options();
        let rel = |v: &[f64], u: f64| -> Vec<f64> { v.iter().map(|t| t - u).collect() };
        let mut v = vec![
            waveform_volts(&rel(fast, u[0]), o.volts_per_um[0], "raster x")
                .map_err(|m| self.err(m))?,
        ];
        if !o.ao[1].is_empty() {
            v.push(
                waveform_volts(&rel(slow, u[1]), o.volts_per_um[1], "raster y")
                    .map_err(|m| self.err(m))?,
            );
        }
        Ok(v)
    }
}

impl NiStreamStage {
    /// Sum mode with the outputs still commanding part of the position (a hand-back that
    /// did not finish): hand it back before USB moves the stage.
    fn usb_in_charge(&mut self) -> Result<(), DeviceError> {
        if self.ext != [0.0; 2] && self.mode() == ExternalInput::Sum {
            self.hold_here()?;
        }
        Ok(())
    }
}

impl Stage for NiStreamStage {
    delegate! {
        to self.stage {
            fn name(&self) -> String;
            fn position(&mut self) -> Result<Pos, DeviceError>;
            fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError>;
            fn move_time_s(&self) -> f64;
            fn move_time_for_s(&self, from: Pos, to: Pos) -> f64;
            fn link_costs(&mut self) -> crate::instrument::link::LinkCosts;
        }
    }
    /// The USB command plus what the outputs command (sum mode).
    fn target(&mut self) -> Result<Pos, DeviceError> {
        let mut t = self.stage.target()?;
        t[0] += self.ext[0];
        t[1] += self.ext[1];
        Ok(t)
    }
    fn move_to(&mut self, target: Pos) -> Result<(), DeviceError> {
        self.usb_in_charge()?;
        self.stage.move_to(target)
    }
    fn move_to_or_abort(&mut self, target: Pos, abort: &AtomicBool) -> Result<bool, DeviceError> {
        self.usb_in_charge()?;
        self.stage.move_to_or_abort(target, abort)
    }
    /// Hold where the stage stands: through the outputs and a hand-back while they command
    /// part of the position, else the Nano-Drive's own hold at its readings.
    fn stop(&mut self) -> Result<(), DeviceError> {
        if self.ext != [0.0; 2] {
            return self.hold_here().map(|_| ());
        }
        self.stage.stop()
    }
    crate::instrument::stage_capabilities!(FrameStream);
}

impl FrameStream for NiStreamStage {
    fn stream_name(&self) -> String {
        format!(
            "{} + NI {}",
            self.stage.name(),
            self.raster.options().qpd.device
        )
    }

    fn rate_hz(&self) -> f64 {
        self.raster.options().qpd.rate_hz
    }

    fn axes(&self) -> (usize, Option<usize>) {
        (0, (!self.raster.options().ao[1].is_empty()).then_some(1))
    }

    fn output_range_um(&self) -> [(f64, f64); 2] {
        use super::raster::{AO_MAX_V, AO_MIN_V};
        let o = self.raster.options();
        [0, 1].map(|i| {
            let s = o.volts_per_um[i];
            if s > 0.0 {
                (AO_MIN_V / s, AO_MAX_V / s)
            } else {
                (f64::NAN, f64::NAN)
            }
        })
    }

    fn start(&mut self, fast: &[f64], slow: &[f64]) -> Result<(), DeviceError> {
        if self.raster.options().external_input == ExternalInput::Sum {
            self.take_over()?;
        }
        let v = self.volts(fast, slow)?;
        self.raster.start_stream(&v)
    }

    fn write(&mut self, fast: &[f64], slow: &[f64]) -> Result<(), DeviceError> {
        let v = self.volts(fast, slow)?;
        self.raster.write(&v)
    }

    fn read(&mut self, n: usize, timeout_s: f64) -> Result<StreamChunk, DeviceError> {
        let c = self.raster.read(n, timeout_s)?;
        let t = std::time::Instant::now();
        let o = self.raster.options();
        let m = c.position_v.len();
        let mut out = StreamChunk {
            sx: Vec::with_capacity(m),
            sy: Vec::with_capacity(m),
            sz: Vec::with_capacity(m),
            fast_um: c
                .position_v
                .iter()
                .map(|v| v / o.position_volts_per_um)
                .collect(),
            convert_s: 0.0,
            clipped: Vec::new(),
        };
        // the QPD's samples, volts → signals as a point read does; inputs at the rail flagged
        for i in 0..m {
            let hit = o.qpd.inputs.clipped(&c.inputs, m, i, o.qpd.range_v);
            if hit.iter().any(|h| *h) && out.clipped.is_empty() {
                out.clipped = vec![0; m];
            }
            if let Some(b) = out.clipped.get_mut(i) {
                *b = crate::instrument::range::clip_bits(hit);
            }
            let v = o.qpd.inputs.signals(&c.inputs, m, i);
            let r = o.qpd.calibration.apply(v, [0.0; 3], 1);
            out.sx.push(r.sx);
            out.sy.push(r.sy);
            out.sz.push(r.sz);
        }
        out.convert_s = t.elapsed().as_secs_f64();
        Ok(out)
    }

    fn buffer_samples(&self) -> usize {
        self.raster.buffer_samples()
    }

    fn hold(&mut self) -> Result<Pos, DeviceError> {
        self.hold_here()
    }

    fn write_space(&mut self) -> Result<Option<usize>, DeviceError> {
        self.raster.space_avail()
    }

    /// x, and y when its output is wired: `MCL_SingleReadN`.
    fn guard_position_um(&mut self, axis: usize) -> Result<Option<f64>, DeviceError> {
        if axis > 1 || (axis == 1 && self.raster.options().ao[1].is_empty()) {
            return Ok(None);
        }
        self.stage.read_now(axis).map(Some)
    }

    fn guards_by_reading(&self) -> bool {
        true
    }

    /// The last frame's measured lag, else the time constant measured on the point moves
    /// (a first-order stage trails a constant-speed target by τ).
    fn lag_s(&self) -> Option<f64> {
        self.lag.or_else(|| self.stage.tau_s())
    }

    fn record_lag_s(&mut self, lag_s: f64) {
        if lag_s.is_finite() && lag_s >= 0.0 {
            self.lag = Some(lag_s);
        }
    }

    fn ran_away(&mut self) -> String {
        self.swapped = true;
        // At once, by the fastest means: configured as "replace", the outputs play absolute
        // targets, and a controller that sums adds them to the USB command. One
        // `MCL_SingleWriteN` of 0 µm per driven axis makes the USB command add nothing: the
        // stage heads back to the outputs' target (the plan) at once, before the tasks are
        // stopped and the hold below is written.
        if self.raster.options().external_input == ExternalInput::Replace {
            let axes = if self.raster.options().ao[1].is_empty() {
                1
            } else {
                2
            };
            for k in 0..axes {
                if let Err(e) = self.stage.command_now(k, 0.0) {
                    return format!("stopping it failed: {e}; {}", self.runaway_advice());
                }
            }
        }
        // at once: a runaway crosses the travel in a few time constants
        let held = match self.hold_here() {
            Ok(p) => format!("the stage was held at x = {:.4}, y = {:.4} µm", p[0], p[1]),
            Err(e) => format!("holding it failed: {e}"),
        };
        format!("{held}; {}", self.runaway_advice())
    }
}
