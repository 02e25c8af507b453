//! Hardware-timed lines, device-neutral: what the raster engine (`acquire::raster`) asks a
//! stage with a wave generator and a data recorder to do, and what it gets back. A PI GCS
//! controller does it with `WAV`/`WGO`/`DRR?` (`gcs/wave.rs`); the simulator with its stage
//! model (`sim/`). Units: µm and s.

/// What a stage's hardware-timed lines can do ([`LineScan::line_timing`](super::LineScan::line_timing)).
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

/// Point `i` (0 ≤ i < n, n ≥ 2) of PI's `LIN` curve from 0 to `amp` over `n` points with `s`
/// points of constant acceleration at each end: the distance from the curve's start. The
/// wave tables the driver writes and the emulator's generator share it.
pub fn lin_point(amp: f64, n: usize, s: usize, i: usize) -> f64 {
    let t = (n - 1) as f64;
    let s = s as f64;
    let v = amp / (t - s);
    let i = i as f64;
    if s > 0.0 && i < s {
        v * i * i / (2.0 * s)
    } else if s > 0.0 && i > t - s {
        let r = t - i;
        amp - v * r * r / (2.0 * s)
    } else {
        v * (i - s / 2.0)
    }
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

impl LineSweep {
    /// The wave table, one absolute position (µm) per wave point: PI's `LIN` curve with
    /// `speedupdown` points of constant acceleration at each end (GCS 2.0 `WAV … LIN`: the
    /// speed is constant between the ramps, and the ramps cover `v·s/2` each, `v` the distance
    /// per point on the constant part, `s` the ramp points).
    pub fn wave(&self) -> Vec<f64> {
        (0..self.points).map(|i| self.wave_at(i)).collect()
    }

    /// Point `i` of [`wave`](Self::wave), µm.
    pub fn wave_at(&self, i: usize) -> f64 {
        let n = self.points;
        if n < 2 {
            return self.from_um;
        }
        self.from_um + lin_point(self.to_um - self.from_um, n, self.speedupdown, i)
    }

    /// The target (the generator's output) at every servo cycle of the wave: point
    /// `⌊j / rate⌋` at cycle `j`, µm.
    pub fn targets_per_cycle(&self) -> Vec<f64> {
        let r = self.rate.max(1) as usize;
        self.wave()
            .into_iter()
            .flat_map(|p| std::iter::repeat_n(p, r))
            .collect()
    }
}

/// The position of an axis following `targets` (one per servo cycle of `dt` s, starting at
/// rest on `targets[0]`) with a first-order lag of time constant `tau` s: per cycle
/// `x += α·(target − x)`, `α = 1 − exp(−dt/τ)` (a closed-loop piezo of bandwidth `1/(2πτ)`;
/// `tau = 0`: no lag, the position is the target). On a ramp of speed `v` the position trails
/// by `v·dt/(exp(dt/τ) − 1)` ≈ `v·(τ − dt/2)`.
pub fn lagged(targets: &[f64], dt: f64, tau: f64) -> Vec<f64> {
    if tau.is_nan() || tau <= 0.0 {
        return targets.to_vec();
    }
    let a = 1.0 - (-dt / tau).exp();
    let mut x = targets.first().copied().unwrap_or(0.0);
    targets
        .iter()
        .map(|&t| {
            x += a * (t - x);
            x
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sweep(points: usize, s: usize) -> LineSweep {
        LineSweep {
            axis: 0,
            from_um: 1.0,
            to_um: 3.0,
            points,
            speedupdown: s,
            rate: 2,
            record_rate: 1,
            trigger_line: None,
            table: 1,
            servo_cycle_s: 50e-6,
        }
    }

    #[test]
    fn the_wave_runs_from_start_to_end_at_constant_speed_between_the_ramps() {
        let s = sweep(101, 10);
        let w = s.wave();
        assert_eq!(w[0], 1.0);
        assert!((w[100] - 3.0).abs() < 1e-12);
        // constant part: v = amp/(t − s) = 2/90 per point
        let v = 2.0 / 90.0;
        for i in 11..90 {
            assert!((w[i + 1] - w[i] - v).abs() < 1e-12, "{i}");
        }
        // speed continuous at the ramp's end: the ramp ends at v·s/2 from the start
        assert!((w[10] - 1.0 - v * 10.0 / 2.0).abs() < 1e-12);
        // speed_um_s is that speed per point over rate · servo cycle
        assert!((s.speed_um_s() - v / (2.0 * 50e-6)).abs() < 1e-9);
        assert_eq!(s.targets_per_cycle().len(), 202);
    }

    #[test]
    fn a_lagged_ramp_trails_by_v_tau() {
        let (dt, tau, v) = (50e-6, 0.5e-3, 100.0); // s, s, µm/s
        let t: Vec<f64> = (0..2000).map(|k| v * dt * k as f64).collect();
        let x = lagged(&t, dt, tau);
        let lag = t[1999] - x[1999];
        let expect = v * dt / ((dt / tau).exp() - 1.0);
        assert!((lag - expect).abs() < 1e-9, "{lag} vs {expect}");
        assert!((expect - v * (tau - dt / 2.0)).abs() < 1e-3 * expect);
        assert_eq!(lagged(&t, dt, 0.0), t);
    }
}
