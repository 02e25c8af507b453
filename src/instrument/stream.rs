//! A raster frame streamed on one clock: a board whose analog outputs drive the stage's
//! external inputs (the fast and the slow axis) and whose inputs record, sample for sample on
//! the outputs' clock, the QPD and the fast axis's position monitor (an NI board on a
//! Nano-Drive, `[raster] backend = "nidaqmx"`). The scan engine's stream strategy
//! (`acquire::strategy::stream`) plans the whole frame's waveform, checks it, writes it ahead
//! of the clock in blocks while it reads the inputs in chunks, and bins each line by the
//! measured position as soon as its samples are in.
//!
//! Units: positions in µm, times in s, rates in Hz.

use super::{DeviceError, Pos};

/// Samples of the inputs in the order taken, from the stream's first sample on.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StreamChunk {
    /// QPD signals through the QPD's calibration (the same as a point read's).
    pub sx: Vec<f64>,
    pub sy: Vec<f64>,
    pub sz: Vec<f64>,
    /// The fast axis's measured position (the position monitor), µm.
    pub fast_um: Vec<f64>,
    /// Per sample, which signals' inputs were at or beyond the rail
    /// ([`super::range::clip_bits`]); empty when none was.
    pub clipped: Vec<u8>,
    /// Wall time spent turning the chunk's volts into signals and positions, s (CPU-bound:
    /// the host's share of the stream's cost).
    pub convert_s: f64,
}

impl StreamChunk {
    pub fn len(&self) -> usize {
        self.fast_um.len()
    }
    pub fn is_empty(&self) -> bool {
        self.fast_um.is_empty()
    }
}

/// A device pair that streams a frame (see the module documentation).
pub trait FrameStream {
    /// For messages: the board and the stage (`"Nano-Drive 2847 + NI Dev1"`).
    fn stream_name(&self) -> String;
    /// The outputs' and inputs' common sample rate, Hz.
    fn rate_hz(&self) -> f64;
    /// The stage axes the outputs drive: (fast, slow). `slow`: `None` when only the fast
    /// axis's output is wired (a frame then cannot step its rows).
    fn axes(&self) -> (usize, Option<usize>);
    /// The positions (µm) each output can command, `[fast, slow]` as (min, max): the external
    /// inputs' voltage range over their scale. A waveform outside is refused before any task.
    fn output_range_um(&self) -> [(f64, f64); 2];
    /// Configure and start the stream: the outputs' first block (`fast`, `slow`, µm per
    /// sample, equal lengths) written, the inputs armed on the outputs' clock and start trigger,
    /// then the outputs started. Refused when a value leaves [`output_range_um`].
    fn start(&mut self, fast: &[f64], slow: &[f64]) -> Result<(), DeviceError>;
    /// Append the next block of the outputs (played after what was written before).
    fn write(&mut self, fast: &[f64], slow: &[f64]) -> Result<(), DeviceError>;
    /// The next `n` samples of the inputs, waiting at most `timeout_s` for them.
    fn read(&mut self, n: usize, timeout_s: f64) -> Result<StreamChunk, DeviceError>;
    /// Samples per channel the inputs' buffer holds (reading later than that overflows).
    fn buffer_samples(&self) -> usize;
    /// Stop and clear the stream's tasks and hold every output at the position the stage
    /// reads now (never 0 V unless it stands at 0 µm); returns that position. Also after a
    /// fault: the tasks are cleared whatever the hold does.
    fn hold(&mut self) -> Result<Pos, DeviceError>;
    /// Samples per output the outputs' buffer can take now (a write of at most this many
    /// never waits); `None`: unknown (the caller keeps its own budget).
    fn write_space(&mut self) -> Result<Option<usize>, DeviceError> {
        Ok(None)
    }
    /// Stage axis `axis`'s position read now (µm), for the guard in the stream's first
    /// milliseconds, where the stage can read it apart from the inputs (a Nano-Drive over
    /// USB); `None`: not readable that way.
    fn guard_position_um(&mut self, _axis: usize) -> Result<Option<f64>, DeviceError> {
        Ok(None)
    }
    /// The guard watches the stage's own readings ([`guard_position_um`](Self::guard_position_um))
    /// while the inputs' next chunk comes in.
    fn guards_by_reading(&self) -> bool {
        false
    }
    /// The stage's lag (s): how long its measured position trails the target at constant
    /// speed, as last measured (a raster's lines, or the settling of point moves); `None`
    /// before anything was measured. Sets a frame's margins.
    fn lag_s(&self) -> Option<f64> {
        None
    }
    /// The lag (s) a frame measured, for the next frame's margins.
    fn record_lag_s(&mut self, _lag_s: f64) {}
    /// The measured position left the plan in the stream's first milliseconds (a stage
    /// that runs away): stop the stream and hold the stage at once, the way that undoes it
    /// (and so every later [`hold`](Self::hold)). Returns what to tell the user: where the
    /// stage was held and the likely cause (a configuration key to check).
    fn ran_away(&mut self) -> String {
        String::new()
    }
}
