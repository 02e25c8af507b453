//! Hardware-timed lines, device-neutral: what the raster engine (`acquire::raster`) asks a
//! stage with a wave generator and a data recorder to do, and what it gets back. A PI GCS
//! controller does it with `WAV`/`WGO`/`DRR?` (`gcs_wave.rs`); the simulator with its stage
//! model (`sim/`). Units: µm and s.

/// What a stage's hardware-timed lines can do ([`Stage::line_timing`](super::Stage::line_timing)).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LineTiming {
    /// The controller's servo cycle, s: the clock of the wave and the recorder.
    pub servo_cycle_s: f64,
    /// Most points one wave table holds.
    pub max_wave_points: usize,
    /// Most samples one record table holds.
    pub max_record_points: usize,
    /// The digital output wired to the digitiser's external trigger (`None`: the digitiser is
    /// started by the stage itself, as in the simulator).
    pub trigger_line: Option<u8>,
}

/// One hardware-timed line.
#[derive(Debug, Clone, PartialEq)]
pub struct LineSweep {
    /// Stage axis swept: 0 = x, 1 = y, 2 = z.
    pub axis: usize,
    /// Start and end of the wave, µm (absolute).
    pub from_um: f64,
    pub to_um: f64,
    /// Wave points, speed-up and speed-down included.
    pub points: usize,
    /// Points of constant acceleration at each end of the wave.
    pub speedupdown: usize,
    /// Servo cycles per wave point (`WTR`).
    pub rate: u32,
    /// Servo cycles per recorded sample (`RTR`).
    pub record_rate: u32,
    /// Digital output (1…3) pulsed at the first wave point; `None`: no trigger output.
    pub trigger_line: Option<u8>,
    /// Wave table used.
    pub table: u32,
    /// The controller's servo cycle, s (for the sweep's duration and its timeout).
    pub servo_cycle_s: f64,
}

impl LineSweep {
    /// Duration of the wave, s: `points · rate · servo cycle`.
    pub fn duration_s(&self) -> f64 {
        self.points as f64 * f64::from(self.rate) * self.servo_cycle_s
    }

    /// Speed on the constant-speed part, µm/s.
    pub fn speed_um_s(&self) -> f64 {
        let steps = self.points as f64 - 1.0 - self.speedupdown as f64;
        (self.to_um - self.from_um).abs() / (steps * f64::from(self.rate) * self.servo_cycle_s)
    }

    /// Recorded samples covering the wave.
    pub fn samples(&self) -> usize {
        let cycles = self.points as u64 * u64::from(self.rate);
        cycles.div_ceil(u64::from(self.record_rate.max(1))) as usize
    }
}

/// What the data recorder gave for one line.
#[derive(Debug, Clone, PartialEq)]
pub struct SweepRecord {
    /// Time between samples, s (`SAMPLE_TIME` of the GCS array header).
    pub sample_time_s: f64,
    /// Commanded (target) position per sample, µm.
    pub target_um: Vec<f64>,
    /// Measured position per sample, µm.
    pub position_um: Vec<f64>,
}
