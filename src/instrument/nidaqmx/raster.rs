//! The NI board's hardware-timed raster, device level: an AO task plays the frame's waveform
//! (fast and slow axis) into the Nano-Drive's external inputs on the board's clock, written
//! ahead of the clock in blocks (regeneration off), and an AI task on the AO task's sample
//! clock (`/DevN/ao/SampleClock`, started by `/DevN/ao/StartTrigger`) records, sample for
//! sample, the QPD inputs and the fast axis's sensor-monitor voltage, read in chunks while the
//! stage sweeps. Both tasks are continuous: no buffer grows with the frame. Binning by
//! measured position is the scan engine's (`acquire::raster::bin_line`), as for every raster.
//!
//! At the end of the frame, on a fault and on Ctrl-C both tasks are stopped and cleared and
//! the outputs are held at the voltage of the present position ([`NiRaster::hold`]: a static
//! AO task writing one value per output), never 0 V.
//!
//! Units: positions in µm, voltages in V, times in s.

use super::ffi::NiDaqmx;
use super::{NiQpdOptions, Task};
use crate::instrument::DeviceError;
use std::sync::Arc;

/// The external inputs' range on a Nano-Drive: 0–10 V over each axis's calibrated range.
pub const AO_MIN_V: f64 = 0.0;
pub const AO_MAX_V: f64 = 10.0;

/// The input range of the sensor-monitor input, ±V: the Nano-Drive's monitor swings 0–10 V
/// over the calibrated range (the PCI-6120's ±10 V range), whatever range the QPD's inputs use.
pub const MONITOR_RANGE_V: f64 = 10.0;

/// Samples per channel read at a time while a line plays (≈ 10 ms at 800 kS/s).
pub const CHUNK: usize = 8192;

/// How a Nano-Drive combines an external input with the position commanded over USB
/// (`[raster] external_input`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExternalInput {
    /// The external input's position is added to the USB command (MCL's documented
    /// behaviour; the default): the outputs play target − USB command.
    Sum,
    /// The controller follows the external input alone while it is driven: the outputs play
    /// the target.
    Replace,
}

impl ExternalInput {
    pub fn parse(s: &str) -> Option<ExternalInput> {
        match s {
            "sum" => Some(ExternalInput::Sum),
            "replace" => Some(ExternalInput::Replace),
            _ => None,
        }
    }
    pub fn as_str(self) -> &'static str {
        match self {
            ExternalInput::Sum => "sum",
            ExternalInput::Replace => "replace",
        }
    }
}

/// The raster's settings (`[raster]` with the `[qpd]` it records).
#[derive(Debug, Clone, PartialEq)]
pub struct NiRasterOptions {
    /// How the controller combines the outputs with its USB command.
    pub external_input: ExternalInput,
    /// The board, its QPD inputs, range, terminal configuration and rate (the AO clock's rate).
    pub qpd: NiQpdOptions,
    /// The outputs wired to the x and y external inputs (y: empty when not wired).
    pub ao: [String; 2],
    /// Volts per µm of the x and y external inputs.
    pub volts_per_um: [f64; 2],
    /// The input wired to the fast (x) axis's sensor-monitor output.
    pub position: String,
    /// Volts per µm of the sensor monitor.
    pub position_volts_per_um: f64,
}

impl NiRasterOptions {
    /// The AO channels in use and their scales: x, and y when wired.
    pub fn outputs(&self) -> Vec<(String, f64)> {
        (0..2)
            .filter(|&i| !self.ao[i].is_empty())
            .map(|i| (self.ao[i].clone(), self.volts_per_um[i]))
            .collect()
    }
}

/// The AO waveform (V) for `targets_um` on an external input of `v_per_um`, refused when a
/// point leaves the input's 0–10 V (`who` names the axis in the message).
pub fn waveform_volts(targets_um: &[f64], v_per_um: f64, who: &str) -> Result<Vec<f64>, String> {
    let mut out = Vec::with_capacity(targets_um.len());
    for (i, &t) in targets_um.iter().enumerate() {
        let v = t * v_per_um;
        if !(v.is_finite() && (AO_MIN_V..=AO_MAX_V).contains(&v)) {
            return Err(format!(
                "{who}: waveform point {i} at {t:.4} µm is {v:.4} V, outside the external input's {AO_MIN_V}–{AO_MAX_V} V \
                 (volts_per_um = {v_per_um})"
            ));
        }
        out.push(v);
    }
    Ok(out)
}

/// One chunk of the stream: QPD inputs (V, acquisition order) and the sensor monitor (V).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Chunk {
    /// The QPD inputs grouped by channel (`NiInputs::signals`' layout): input `c`'s samples
    /// at `c·n … c·n + n`, `n` = `position_v.len()`.
    pub inputs: Vec<f64>,
    pub position_v: Vec<f64>,
}

/// The raster tasks of one board.
pub struct NiRaster {
    lib: Arc<NiDaqmx>,
    opts: NiRasterOptions,
    name: String,
    ao: Option<Task>,
    ai: Option<Task>,
    /// Samples per channel the AI buffer holds.
    buffer: usize,
    buf: Vec<f64>,
}

impl NiRaster {
    pub fn new(lib: Arc<NiDaqmx>, opts: NiRasterOptions, name: String) -> NiRaster {
        NiRaster {
            lib,
            opts,
            name,
            ao: None,
            ai: None,
            buffer: 0,
            buf: Vec::new(),
        }
    }

    pub fn options(&self) -> &NiRasterOptions {
        &self.opts
    }

    fn dev(&self) -> &str {
        &self.opts.qpd.device
    }

    /// The AI buffer for a stream at `rate`: two seconds of samples (at least [`CHUNK`] × 4),
    /// so that the reader may fall behind by a line's binning and an engine's autosave.
    pub fn buffer_for(rate: f64) -> usize {
        ((2.0 * rate) as usize).max(4 * CHUNK)
    }

    /// Configure and start the stream: an AO task on the board's clock, continuous, with
    /// regeneration off (`DAQmxSetWriteRegenMode(DAQmx_Val_DoNotAllowRegen)`: the outputs
    /// play each sample written once, and the waveform is written ahead of the clock in
    /// blocks), `volts[c]` per output (x, then y when wired) as its first block; an AI task
    /// (QPD inputs + sensor monitor) on the AO sample clock, continuous, started by the AO
    /// start trigger; AI started (it waits for the trigger), then AO.
    pub fn start_stream(&mut self, volts: &[Vec<f64>]) -> Result<(), DeviceError> {
        self.clear();
        let outs = self.opts.outputs();
        let n = volts.first().map_or(0, Vec::len);
        if volts.len() != outs.len() || n < 2 || volts.iter().any(|v| v.len() != n) {
            return Err(DeviceError::Other {
                device: self.name.clone(),
                detail: format!(
                    "a raster stream needs one block of ≥ 2 samples per output ({} outputs, got {} blocks)",
                    outs.len(),
                    volts.len()
                ),
            });
        }
        let rate = self.opts.qpd.rate_hz;
        let dev = self.dev().to_string();
        let Some(regen) = self.lib.set_write_regen_mode else {
            return Err(DeviceError::Other {
                device: self.name.clone(),
                detail: format!(
                    "{} has no DAQmxSetWriteRegenMode: the raster stream writes its waveform ahead of the clock and needs it",
                    self.lib.path.display()
                ),
            });
        };
        let ao = Task::create(self.lib.clone(), &self.name, "bfpscope-raster-ao")?;
        for (ch, _) in &outs {
            ao.add_ao(&format!("{dev}/{ch}"), AO_MIN_V, AO_MAX_V)?;
        }
        // continuous: sampsPerChan is a buffer hint; the first write sizes the buffer
        ao.timing("", rate, true, n as u64)?;
        // SAFETY: `int32 DAQmxSetWriteRegenMode(TaskHandle taskHandle, int32 data)`.
        let r = unsafe { regen(ao.handle(), super::ffi::DAQMX_VAL_DO_NOT_ALLOW_REGEN) };
        super::check(
            ao.lib(),
            &self.name,
            || {
                format!(
                    "DAQmxSetWriteRegenMode(task \"{}\", DAQmx_Val_DoNotAllowRegen)",
                    ao.name
                )
            },
            r,
        )?;
        Self::write_block(&ao, &self.name, volts)?;
        let ai = Task::create(self.lib.clone(), &self.name, "bfpscope-raster-ai")?;
        for ch in self.opts.qpd.inputs.names() {
            ai.add_ai(
                &format!("{dev}/{ch}"),
                self.opts.qpd.terminal,
                self.opts.qpd.range_v,
            )?;
        }
        // the sensor monitor swings 0–10 V whatever the QPD's range: its own range, so that
        // a QPD range chosen for small signals does not clip the measured position
        ai.add_ai(
            &format!("{dev}/{}", self.opts.position),
            self.opts.qpd.terminal,
            MONITOR_RANGE_V,
        )?;
        // continuous mode sizes its buffer from sampsPerChan
        let buffer = Self::buffer_for(rate);
        ai.timing(&format!("/{dev}/ao/SampleClock"), rate, true, buffer as u64)?;
        ai.start_trigger(&format!("/{dev}/ao/StartTrigger"))?;
        ai.start()?;
        ao.start()?;
        self.ao = Some(ao);
        self.ai = Some(ai);
        self.buffer = buffer;
        Ok(())
    }

    fn write_block(ao: &Task, name: &str, volts: &[Vec<f64>]) -> Result<(), DeviceError> {
        let n = volts.first().map_or(0, Vec::len);
        let data: Vec<f64> = volts.iter().flatten().copied().collect();
        let wrote = ao.write(n, false, 10.0, &data)?;
        if wrote != n {
            return Err(DeviceError::Garbled {
                device: name.to_string(),
                command: "DAQmxWriteAnalogF64".into(),
                reply: format!("{wrote} samples per channel written, {n} given"),
            });
        }
        Ok(())
    }

    /// Append a block to the running AO stream (`volts[c]` per output, equal lengths).
    pub fn write(&mut self, volts: &[Vec<f64>]) -> Result<(), DeviceError> {
        let Some(ao) = &self.ao else {
            return Err(DeviceError::Other {
                device: self.name.clone(),
                detail: "write: no raster stream running".into(),
            });
        };
        Self::write_block(ao, &self.name, volts)
    }

    /// Samples per channel the AI buffer holds.
    pub fn buffer_samples(&self) -> usize {
        self.buffer
    }

    /// Read the next `n` samples per channel, waiting at most `timeout_s` for them.
    pub fn read(&mut self, n: usize, timeout_s: f64) -> Result<Chunk, DeviceError> {
        let Some(ai) = &self.ai else {
            return Err(DeviceError::Other {
                device: self.name.clone(),
                detail: "read: no raster stream running".into(),
            });
        };
        if n == 0 {
            return Ok(Chunk::default());
        }
        let chans = self.opts.qpd.inputs.names().len() + 1;
        self.buf.resize(chans * n, 0.0);
        let got = ai.read(n, timeout_s, &mut self.buf)?;
        let block = |k: usize| &self.buf[k * n..k * n + got];
        Ok(Chunk {
            inputs: (0..chans - 1).flat_map(block).copied().collect(),
            position_v: block(chans - 1).to_vec(),
        })
    }

    /// Stop and clear both tasks (each is cleared even if stopping failed).
    pub fn clear(&mut self) {
        self.ai = None; // Task::drop stops and clears
        self.ao = None;
    }

    /// Stop and clear the line's tasks, then hold each output at `um` (x, y) × its scale
    /// (see [`Self::hold_volts`]). Never 0 V unless the position is 0 µm.
    pub fn hold(&mut self, um: [f64; 2]) -> Result<(), DeviceError> {
        let s = self.opts.volts_per_um;
        self.hold_volts([um[0] * s[0], um[1] * s[1]])
    }

    /// Stop and clear the line's tasks, then hold each output at `volts` (x, y; clamped to
    /// 0–10 V) through a static AO task, cleared again (the board keeps the last value
    /// written).
    pub fn hold_volts(&mut self, volts: [f64; 2]) -> Result<(), DeviceError> {
        self.clear();
        let outs = self.opts.outputs();
        let dev = self.dev().to_string();
        let t = Task::create(self.lib.clone(), &self.name, "bfpscope-raster-hold")?;
        let mut values = Vec::new();
        for (i, (ch, _)) in outs.iter().enumerate() {
            t.add_ao(&format!("{dev}/{ch}"), AO_MIN_V, AO_MAX_V)?;
            values.push(volts[i].clamp(AO_MIN_V, AO_MAX_V));
        }
        t.write(1, true, 1.0, &values)?;
        Ok(())
    }

    /// Samples per channel the running stream's output buffer can take now
    /// (`DAQmxGetWriteSpaceAvail`); `None` when the library lacks it or no stream runs.
    pub fn space_avail(&self) -> Result<Option<usize>, DeviceError> {
        let (Some(ao), Some(f)) = (&self.ao, self.lib.get_write_space_avail) else {
            return Ok(None);
        };
        let mut v: u32 = 0;
        // SAFETY: `int32 DAQmxGetWriteSpaceAvail(TaskHandle taskHandle, uInt32 *data)`.
        let r = unsafe { f(ao.handle(), &mut v) };
        super::check(
            ao.lib(),
            &self.name,
            || format!("DAQmxGetWriteSpaceAvail(task \"{}\", &space)", ao.name),
            r,
        )?;
        Ok(Some(v as usize))
    }
}

impl Drop for NiRaster {
    fn drop(&mut self) {
        self.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn waveforms_convert_and_refuse_points_outside_0_to_10_v() {
        let v = waveform_volts(&[0.0, 37.5, 75.0], 0.1333, "x").unwrap();
        assert_eq!(v[0], 0.0);
        assert!((v[1] - 4.99875).abs() < 1e-12);
        assert!((v[2] - 9.9975).abs() < 1e-12);
        let e = waveform_volts(&[10.0, 76.0], 0.1333, "x").unwrap_err();
        assert!(
            e.starts_with("x: waveform point 1 at 76.0000 µm is 10.1308 V"),
            "{e}"
        );
        let e = waveform_volts(&[-0.5], 0.1333, "x").unwrap_err();
        assert!(
            e.starts_with("x: waveform point 0 at -0.5000 µm is -0.06")
                && e.contains("outside the external input's 0–10 V"),
            "{e}"
        );
        let e = waveform_volts(&[f64::NAN], 0.1333, "x").unwrap_err();
        assert!(
            e.starts_with("x: waveform point 0 at NaN µm is NaN V"),
            "{e}"
        );
    }
}
