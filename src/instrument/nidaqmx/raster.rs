//! The NI board's hardware-timed raster, device level: an AO task plays the fast axis's
//! waveform into the Nano-Drive's external input on the board's clock, and an AI task on the
//! AO task's sample clock (`/DevN/ao/SampleClock`, started by `/DevN/ao/StartTrigger`) records,
//! sample for sample, the QPD inputs and the fast axis's sensor-monitor voltage. The AI task is
//! continuous and read in chunks while the stage sweeps (no buffer grows with the line); the AO
//! task is finite (one line). Binning by measured position is the scan engine's
//! (`acquire::raster::bin_line`), as for every raster.
//!
//! At the end of a line, on a fault and on Ctrl-C both tasks are stopped and cleared and the
//! outputs are held at the voltage of the present position ([`NiRaster::hold`]: a static AO
//! task writing one value per output), never 0 V.
//!
//! Units: positions in µm, voltages in V, times in s.

use super::ffi::NiDaqmx;
use super::{NiQpdOptions, Task};
use crate::instrument::DeviceError;
use std::sync::Arc;

/// The external inputs' range on a Nano-Drive: 0–10 V over each axis's calibrated range.
pub const AO_MIN_V: f64 = 0.0;
pub const AO_MAX_V: f64 = 10.0;

/// Samples per channel read at a time while a line plays (≈ 10 ms at 800 kS/s).
pub const CHUNK: usize = 8192;

/// The raster's settings (`[raster]` with the `[qpd]` it records).
#[derive(Debug, Clone, PartialEq)]
pub struct NiRasterOptions {
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

/// One chunk of a line: QPD inputs (V, acquisition order) and the sensor monitor (V).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Chunk {
    /// `inputs[c][k]`: input `c` of the QPD, sample `k`.
    pub inputs: Vec<Vec<f64>>,
    pub position_v: Vec<f64>,
}

/// The raster tasks of one board.
pub struct NiRaster {
    lib: Arc<NiDaqmx>,
    opts: NiRasterOptions,
    name: String,
    ao: Option<Task>,
    ai: Option<Task>,
    /// Samples per channel of the line configured.
    n: usize,
    /// Samples per channel read so far.
    read: usize,
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
            n: 0,
            read: 0,
            buf: Vec::new(),
        }
    }

    pub fn options(&self) -> &NiRasterOptions {
        &self.opts
    }

    fn dev(&self) -> &str {
        &self.opts.qpd.device
    }

    /// Configure a line: `volts[c]` per AO output (x, then y when wired), all the same length
    /// n, played at the QPD rate; the AI task (QPD inputs + sensor monitor) on the AO sample
    /// clock, continuous, started by the AO start trigger. Nothing plays until [`start`].
    pub fn configure(&mut self, volts: &[Vec<f64>]) -> Result<(), DeviceError> {
        self.clear();
        let outs = self.opts.outputs();
        let n = volts.first().map_or(0, Vec::len);
        if volts.len() != outs.len() || n < 2 || volts.iter().any(|v| v.len() != n) {
            return Err(DeviceError::Other {
                device: self.name.clone(),
                detail: format!(
                    "a raster line needs one waveform of ≥ 2 points per output ({} outputs, got {} waveforms)",
                    outs.len(),
                    volts.len()
                ),
            });
        }
        let rate = self.opts.qpd.rate_hz;
        let dev = self.dev().to_string();
        let ao = Task::create(self.lib.clone(), &self.name, "bfpscope-raster-ao")?;
        for (ch, _) in &outs {
            ao.add_ao(&format!("{dev}/{ch}"), AO_MIN_V, AO_MAX_V)?;
        }
        ao.timing("", rate, false, n as u64)?;
        let data: Vec<f64> = volts.iter().flatten().copied().collect();
        let wrote = ao.write(n, false, 10.0, &data)?;
        if wrote != n {
            return Err(DeviceError::Garbled {
                device: self.name.clone(),
                command: "DAQmxWriteAnalogF64".into(),
                reply: format!("{wrote} samples per channel written, {n} given"),
            });
        }
        let ai = Task::create(self.lib.clone(), &self.name, "bfpscope-raster-ai")?;
        for ch in self.opts.qpd.inputs.names() {
            ai.add_ai(
                &format!("{dev}/{ch}"),
                self.opts.qpd.terminal,
                self.opts.qpd.range_v,
            )?;
        }
        ai.add_ai(
            &format!("{dev}/{}", self.opts.position),
            self.opts.qpd.terminal,
            self.opts.qpd.range_v,
        )?;
        // the buffer: a second of samples or the line, whichever is longer (continuous mode
        // sizes its buffer from sampsPerChan)
        let buffer = (n.max(rate as usize)).max(4 * CHUNK) as u64;
        ai.timing(&format!("/{dev}/ao/SampleClock"), rate, true, buffer)?;
        ai.start_trigger(&format!("/{dev}/ao/StartTrigger"))?;
        self.ao = Some(ao);
        self.ai = Some(ai);
        self.n = n;
        self.read = 0;
        Ok(())
    }

    /// Start the AI task (it waits for the AO start trigger), then the AO task.
    pub fn start(&mut self) -> Result<(), DeviceError> {
        let (Some(ai), Some(ao)) = (&self.ai, &self.ao) else {
            return Err(DeviceError::Other {
                device: self.name.clone(),
                detail: "start: no raster line configured".into(),
            });
        };
        ai.start()?;
        ao.start()?;
        self.read = 0;
        Ok(())
    }

    /// Samples per channel of the configured line, and read so far.
    pub fn progress(&self) -> (usize, usize) {
        (self.n, self.read)
    }

    /// Read the next chunk (at most [`CHUNK`] samples per channel, fewer at the line's end),
    /// waiting at most `timeout_s` for it. An empty chunk when the line was read completely.
    pub fn read_chunk(&mut self, timeout_s: f64) -> Result<Chunk, DeviceError> {
        let Some(ai) = &self.ai else {
            return Err(DeviceError::Other {
                device: self.name.clone(),
                detail: "read: no raster line configured".into(),
            });
        };
        let want = (self.n - self.read).min(CHUNK);
        if want == 0 {
            return Ok(Chunk::default());
        }
        let chans = self.opts.qpd.inputs.names().len() + 1;
        self.buf.resize(chans * want, 0.0);
        let got = ai.read(want, timeout_s, &mut self.buf)?;
        self.read += got;
        let mut c = Chunk::default();
        for k in 0..chans - 1 {
            c.inputs.push(self.buf[k * want..k * want + got].to_vec());
        }
        c.position_v = self.buf[(chans - 1) * want..(chans - 1) * want + got].to_vec();
        Ok(c)
    }

    /// Stop and clear both tasks (each is cleared even if stopping failed).
    pub fn clear(&mut self) {
        self.ai = None; // Task::drop stops and clears
        self.ao = None;
    }

    /// Stop and clear the line's tasks, then hold each output at `um` (x, y) through a static
    /// AO task, cleared again (the board keeps the last value written). Never 0 V unless the
    /// position is 0 µm.
    pub fn hold(&mut self, um: [f64; 2]) -> Result<(), DeviceError> {
        self.clear();
        let outs = self.opts.outputs();
        let dev = self.dev().to_string();
        let t = Task::create(self.lib.clone(), &self.name, "bfpscope-raster-hold")?;
        let mut values = Vec::new();
        for (i, (ch, s)) in outs.iter().enumerate() {
            t.add_ao(&format!("{dev}/{ch}"), AO_MIN_V, AO_MAX_V)?;
            values.push((um[i] * s).clamp(AO_MIN_V, AO_MAX_V));
        }
        t.write(1, true, 1.0, &values)?;
        Ok(())
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
        assert!(waveform_volts(&[-0.5], 0.1333, "x").is_err());
        assert!(waveform_volts(&[f64::NAN], 0.1333, "x").is_err());
    }
}
