//! A Nano-Drive whose x and y external inputs are driven by the NI board's outputs
//! (`[raster] backend = "nidaqmx"`): point moves, positions, travel and stop are the
//! Nano-Drive's (Madlib); a raster frame is the board's, streamed on its clock
//! ([`FrameStream`]): the frame's waveform in volts on ao x/y, written ahead in blocks, and
//! the QPD inputs with the x sensor monitor on the AO sample clock, read in chunks.
//!
//! The Nano-Drive is assumed to follow whichever of its inputs changed last (external input or
//! USB command; docs/hardware.md §12): the outputs are only ever written with the position the
//! stage is at (the frame's first sample, a hold) or the frame's own waveform, which starts
//! there.

use super::raster::{waveform_volts, NiRaster};
use crate::instrument::madlib::MadlibStage;
use crate::instrument::stream::{FrameStream, StreamChunk};
use crate::instrument::{DeviceError, Pos, Stage};
use delegate::delegate;
use std::sync::atomic::AtomicBool;

/// A Nano-Drive with NI-driven external inputs.
pub struct NiStreamStage {
    stage: MadlibStage,
    raster: NiRaster,
}

impl NiStreamStage {
    pub fn new(stage: MadlibStage, raster: NiRaster) -> NiStreamStage {
        NiStreamStage { stage, raster }
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

    /// µm per output → volts per output (x, then y when wired), refused outside 0–10 V.
    fn volts(&self, fast: &[f64], slow: &[f64]) -> Result<Vec<Vec<f64>>, DeviceError> {
        let o = self.raster.options();
        let mut v =
            vec![waveform_volts(fast, o.volts_per_um[0], "raster x").map_err(|m| self.err(m))?];
        if !o.ao[1].is_empty() {
            v.push(waveform_volts(slow, o.volts_per_um[1], "raster y").map_err(|m| self.err(m))?);
        }
        Ok(v)
    }
}

impl Stage for NiStreamStage {
    delegate! {
        to self.stage {
            fn name(&self) -> String;
            fn position(&mut self) -> Result<Pos, DeviceError>;
            fn target(&mut self) -> Result<Pos, DeviceError>;
            fn move_to(&mut self, target: Pos) -> Result<(), DeviceError>;
            fn move_to_or_abort(&mut self, target: Pos, abort: &AtomicBool) -> Result<bool, DeviceError>;
            fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError>;
            fn stop(&mut self) -> Result<(), DeviceError>;
            fn move_time_s(&self) -> f64;
        }
    }
    fn frame_stream(&mut self) -> Option<&mut dyn FrameStream> {
        Some(self)
    }
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
        // the tasks first: the outputs keep their last sample and the stage comes to rest
        // on it; then the position it reads now is what the outputs hold
        self.raster.clear();
        let p = self.stage.position()?;
        self.raster.hold([p[0], p[1]])?;
        Ok(p)
    }
}
