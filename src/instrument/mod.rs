//! Instruments: the `Stage` and `Qpd` traits every backend implements (simulated, serial
//! drivers), the clock that settle/dwell times advance, and device errors.
//!
//! Drivers only move, read and report their travel and capabilities. Soft limits, step limits,
//! abort and return-to-start live in `acquire/`; the config file and connecting what it names
//! in `config/`. Nothing here imports either (tests/architecture.rs).

pub mod mock;
pub mod sim;
pub mod trace;
// Hardware: serial drivers, emulators, config, connect.
pub mod emulation;
pub mod emulator;
pub mod family;
pub mod gcs;
pub mod line;
pub mod link;
pub mod madlib;
pub mod nidaqmx;
pub mod range;
pub mod redpitaya;
pub mod registry;
pub mod scpi;
pub mod scpi_session;
pub mod stream;
pub mod tables;
pub mod thorlabs;
pub mod vendor;

pub mod device;

pub use device::{DeviceError, Pos, AXES};
use std::fmt;

/// One QPD reading: the mean of `n` samples of Sx, Sy, Sz and their standard deviations
/// (signals normalised to the beam power for the simulator; volts × calibration for hardware).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct QpdReading {
    pub sx: f64,
    pub sy: f64,
    pub sz: f64,
    pub sx_std: f64,
    pub sy_std: f64,
    pub sz_std: f64,
    pub n: usize,
    /// Samples of Sx, Sy, Sz at or beyond the input's rail among the `n` (see
    /// [`range`]); zeros when none, or when the digitiser does not know its range.
    #[serde(default)]
    pub clipped: [usize; 3],
}

impl fmt::Display for QpdReading {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "sx = {:.6e} ± {:.1e}, sy = {:.6e} ± {:.1e}, sz = {:.6e} ± {:.1e} (n = {})",
            self.sx, self.sx_std, self.sy, self.sy_std, self.sz, self.sz_std, self.n
        )
    }
}

/// A time source. The simulator's is virtual (waiting advances a counter, costing no wall
/// time); hardware uses the wall clock.
pub trait Clock: Send + Sync {
    /// Seconds since the clock started.
    fn now(&self) -> f64;
    /// Wait `seconds` (virtual clocks just advance).
    fn wait(&self, seconds: f64);
    /// True when time is simulated.
    fn is_virtual(&self) -> bool;
}

/// Strain gauges the user zeroes (Thorlabs KPZ101: the "zeroed" status bit, read at connect
/// and kept after a zeroing): a capability of the Thorlabs family.
pub trait GaugeZero {
    /// Whether each axis' gauge is zeroed.
    fn gauge_zeroed(&self) -> [bool; 3];
    /// Zero the gauges (KPZ101: `MGMSG_PZ_SET_ZERO`, then wait for "zeroed"; the actuators go
    /// to their zero and hold there).
    fn zero_gauge(&mut self) -> Result<[bool; 3], DeviceError>;
}

/// Hardware-timed lines: a wave generator playing the fast axis under the controller's clock,
/// its trigger output starting the digitiser, a data recorder measuring the positions (PI GCS
/// `WAV`/`WGO`/`DRR?`; the simulator's model of them): a capability of the families that have
/// them. The raster engine (`acquire::strategy::line`) drives it.
pub trait LineScan {
    /// What the wave generator and the recorder can do; `None` when they cannot serve a raster.
    fn line_timing(&mut self) -> Result<Option<line::LineTiming>, DeviceError>;
    /// Wall time a hardware-timed line `s` costs beyond its wave's own duration, s, for the
    /// raster ETA: starting it, seeing it end, reading the recorder back over the link. 0 when
    /// unknown (the default).
    fn line_overhead_s(&self, s: &line::LineSweep) -> f64 {
        let _ = s;
        0.0
    }
    /// Load the line `s` into the controller (wave, generator, trigger output, recorder).
    /// Nothing moves. The stage sits at the wave's first point (the engine moved it there).
    fn configure_line(&mut self, s: &line::LineSweep) -> Result<(), DeviceError>;
    /// Start the configured line (PI: `WGO g 1`): the digitiser's trigger and the recorder
    /// start with it.
    fn start_line(&mut self, s: &line::LineSweep) -> Result<(), DeviceError>;
    /// Wait until the line has been played. `Ok(false)`: `abort` was raised, the generator
    /// and the axes were stopped. A line still running well past its duration is a fault.
    fn wait_line(
        &mut self,
        s: &line::LineSweep,
        abort: &std::sync::atomic::AtomicBool,
    ) -> Result<bool, DeviceError>;
    /// The recorder's target and measured position of every sample of the line just played.
    fn read_line_record(&mut self, s: &line::LineSweep) -> Result<line::SweepRecord, DeviceError>;
    /// Stop a line (PI: `WGO g 0`, then `STP`): the generator off, every axis stopped. Sent
    /// after Ctrl-C and after any fault during a raster; both commands go out even if the
    /// first fails.
    fn stop_line(&mut self, s: &line::LineSweep) -> Result<(), DeviceError>;
}

/// Raw queries in the controller's command language, for debugging at the prompt
/// (`gcs_query("SAI?")`): a capability of the PI GCS family. Only queries: anything that
/// could move is refused by the driver.
pub trait RawQuery {
    /// The controller's reply lines to `query`.
    fn raw_query(&mut self, query: &str) -> Result<Vec<String>, DeviceError>;
}

/// The vendor operations a stage may offer beyond the [`Stage`] methods every stage has, by
/// name: what [`Stage::capabilities`] is asked for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CapabilityKind {
    GaugeZero,
    Lines,
    RawQuery,
    FrameStream,
}

/// A vendor operation a stage offers ([`Stage::capabilities`]): the stage seen through the
/// capability's trait.
pub enum Capability<'a> {
    /// Strain gauges to zero (Thorlabs KPZ101).
    GaugeZero(&'a mut dyn GaugeZero),
    /// Hardware-timed lines (PI GCS wave generator and recorder; the simulator).
    Lines(&'a mut dyn LineScan),
    /// Raw queries in the controller's language (PI GCS).
    RawQuery(&'a mut dyn RawQuery),
    /// Frames streamed on a board's clock (the NI board driving a Nano-Drive).
    FrameStream(&'a mut dyn stream::FrameStream),
}

/// A stage's [`Stage::capabilities`]: the vendor operations it offers, named as
/// [`CapabilityKind`] and [`Capability`] name them (the stage implements each one's trait).
/// Written inside its `impl Stage`: `stage_capabilities!(Lines, RawQuery);`.
macro_rules! stage_capabilities {
    ($($cap:ident),+ $(,)?) => {
        fn capabilities(
            &mut self,
            kind: $crate::instrument::CapabilityKind,
        ) -> Option<$crate::instrument::Capability<'_>> {
            match kind {
                $($crate::instrument::CapabilityKind::$cap => {
                    Some($crate::instrument::Capability::$cap(self))
                })+
                #[allow(unreachable_patterns)]
                _ => None,
            }
        }
    };
}
pub(crate) use stage_capabilities;

/// A three-axis positioning stage. Positions in µm.
pub trait Stage: Send {
    /// Human-readable device name for messages (`"sim stage"`, `"PI E-727 on /dev/ttyUSB0"`).
    fn name(&self) -> String;
    /// Current position (µm), as measured.
    fn position(&mut self) -> Result<Pos, DeviceError>;
    /// The last commanded target (µm): relative moves and return-to-start start from it, as PI
    /// defines `MVR`, so that repeated relative moves do not accumulate the position noise.
    /// Devices that do not distinguish the two return the position.
    fn target(&mut self) -> Result<Pos, DeviceError> {
        self.position()
    }
    /// Absolute move; returns when the controller reports on-target (or errors).
    fn move_to(&mut self, target: Pos) -> Result<(), DeviceError>;
    /// As `move_to`, but the wait for on-target ends early with `Ok(false)` when `abort` is
    /// raised (Ctrl-C): the axes may still be moving and the caller stops them (`stop`).
    /// `Ok(true)`: on target. Devices whose moves return at once keep the default.
    fn move_to_or_abort(
        &mut self,
        target: Pos,
        _abort: &std::sync::atomic::AtomicBool,
    ) -> Result<bool, DeviceError> {
        self.move_to(target).map(|()| true)
    }
    /// Switch the device on for motion after the connect step's checks (PI: the servos, `SVO`,
    /// for the axes `SVO?` found off), so a connect refused for its limits leaves the device as
    /// it was found. Devices with nothing to switch keep the default.
    fn enable(&mut self) -> Result<(), DeviceError> {
        Ok(())
    }
    /// Travel range per axis (min, max) in µm, as the controller reports it.
    fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError>;
    /// Stop all motion at once.
    fn stop(&mut self) -> Result<(), DeviceError>;
    /// Set the closed-loop velocity of every axis (µm/s) for all later moves, when the device
    /// has one (PI: `VEL`); the connect step sends the `[safety]` speed limit. Devices without
    /// a velocity setting accept it and do nothing.
    fn set_velocity(&mut self, _um_s: f64) -> Result<(), DeviceError> {
        Ok(())
    }
    /// The velocity per axis (µm/s) the device reports (PI: `VEL?`), when it has one.
    fn velocity(&mut self) -> Result<Option<Pos>, DeviceError> {
        Ok(None)
    }
    /// The vendor operation `kind` when this stage offers it (its family implements the
    /// capability's trait), else `None` (the default). Asked through the helpers on
    /// `dyn Stage`: `gauge`, `lines`, `raw_query`, `frame_stream`.
    fn capabilities(&mut self, kind: CapabilityKind) -> Option<Capability<'_>> {
        let _ = kind;
        None
    }
    /// Time a move takes before it returns, for the scan ETA: the simulated stage's model, or
    /// the running mean of the moves measured so far (PI GCS: `MOV` to on target, link
    /// included); 0 when unknown.
    fn move_time_s(&self) -> f64 {
        0.0
    }
    /// Time a move from `from` to `to` (µm) takes before it returns, for the scan ETA: a
    /// model of the device where it has one (Madlib: its calls at their measured cost and the
    /// stage's measured settling for that step), else [`move_time_s`](Self::move_time_s).
    fn move_time_for_s(&self, from: Pos, to: Pos) -> f64 {
        let _ = (from, to);
        self.move_time_s()
    }
    /// What each kind of command cost on the device's link since the last call (count, bytes,
    /// write and reply time), for the scan's per-phase timing; empty for backends without a
    /// command link.
    fn link_costs(&mut self) -> link::LinkCosts {
        Vec::new()
    }
}

/// The capabilities of a stage, asked by name ([`Stage::capabilities`]).
impl<'s> dyn Stage + 's {
    /// The strain gauges this stage lets the user zero ([`CapabilityKind::GaugeZero`]).
    pub fn gauge(&mut self) -> Option<&mut dyn GaugeZero> {
        match self.capabilities(CapabilityKind::GaugeZero) {
            Some(Capability::GaugeZero(g)) => Some(g),
            _ => None,
        }
    }
    /// This stage's hardware-timed lines ([`CapabilityKind::Lines`]).
    pub fn lines(&mut self) -> Option<&mut dyn LineScan> {
        match self.capabilities(CapabilityKind::Lines) {
            Some(Capability::Lines(l)) => Some(l),
            _ => None,
        }
    }
    /// This stage's hardware-timed lines for `call`, or the error saying it has none.
    pub fn lines_for(&mut self, call: &str) -> Result<&mut dyn LineScan, DeviceError> {
        let name = self.name();
        self.lines().ok_or_else(|| no_lines(name, call))
    }
    /// What the stage's hardware-timed lines can do: `None` for a stage without them (the
    /// raster engine then refuses `mode: "raster"`).
    pub fn line_timing(&mut self) -> Result<Option<line::LineTiming>, DeviceError> {
        match self.lines() {
            Some(l) => l.line_timing(),
            None => Ok(None),
        }
    }
    /// Stop a line: the lines' own stop, or (a stage without lines) the stage's.
    pub fn stop_line(&mut self, s: &line::LineSweep) -> Result<(), DeviceError> {
        match self.lines() {
            Some(l) => l.stop_line(s),
            None => self.stop(),
        }
    }
    /// The controller's reply lines to a raw query ([`CapabilityKind::RawQuery`]), or the
    /// error saying this stage has no command language to query.
    pub fn raw_query(&mut self, query: &str) -> Result<Vec<String>, DeviceError> {
        let name = self.name();
        match self.capabilities(CapabilityKind::RawQuery) {
            Some(Capability::RawQuery(q)) => q.raw_query(query),
            _ => Err(DeviceError::Other {
                device: name,
                detail: format!("`{query}`: this stage has no command language to query"),
            }),
        }
    }
    /// The frame stream of a stage driven by a board's analog outputs on the board's clock
    /// (`[raster] backend = "nidaqmx"`; [`CapabilityKind::FrameStream`]); `None` for every
    /// other stage. A raster on a stage that has one is streamed (`acquire::strategy::stream`).
    pub fn frame_stream(&mut self) -> Option<&mut dyn stream::FrameStream> {
        match self.capabilities(CapabilityKind::FrameStream) {
            Some(Capability::FrameStream(f)) => Some(f),
            _ => None,
        }
    }
}

fn no_lines(device: String, call: &str) -> DeviceError {
    DeviceError::Other {
        device,
        detail: format!(
            "{call}: this stage has no wave generator and data recorder for hardware-timed lines"
        ),
    }
}

/// QPD samples per point for a dwell time: round(dwell · rate), at least 1.
pub fn samples_per_point(dwell_s: f64, rate_hz: f64) -> usize {
    ((dwell_s * rate_hz).round() as usize).max(1)
}

/// A quadrant-photodiode digitiser.
pub trait Qpd: Send {
    fn name(&self) -> String;
    /// Sampling rate in Hz (a read of `n` samples takes `n / rate` seconds).
    fn sample_rate(&self) -> f64;
    /// Average `n` samples of (Sx, Sy, Sz). The read itself takes the time it takes: the
    /// simulated QPD advances the virtual clock by `n / sample_rate`.
    fn read(&mut self, n: usize) -> Result<QpdReading, DeviceError>;
    /// As `read`, for a caller that uses the means only (the scan engine stores Sx, Sy, Sz per
    /// pixel, not their standard deviations): a device may then ask for less (the SCPI
    /// digitiser: `MEAS:QPD?`, three numbers, instead of six). The standard deviations of the
    /// result may be 0.
    fn read_means(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        self.read(n)
    }
    /// The signal averaged over `duration_s` seconds (a point's dwell), for a caller that uses
    /// the means only, as [`read_means`](Self::read_means). By default `read_means` of
    /// [`samples_per_point`]`(duration_s, sample_rate)` samples; a digitiser whose acquisition
    /// is set by a time window (the Red Pitaya: decimation and sample count from the window)
    /// reads the window itself, with no round trip through a nominal sample count.
    fn read_for(&mut self, duration_s: f64) -> Result<QpdReading, DeviceError> {
        self.read_means(samples_per_point(duration_s, self.sample_rate()))
    }
    /// What produced the signal, for scan metadata: the simulator reports its render pipeline
    /// (stages built and the wall time spent in each); hardware reports nothing extra.
    fn metadata(&self) -> Option<serde_json::Value> {
        None
    }
    /// The inputs' range and the sum floor ([`range::InputRange`]): what a clipped sample
    /// and a dark pixel are. `None` (the default): unknown, nothing is counted.
    fn input_range(&self) -> Option<range::InputRange> {
        None
    }
    /// Arm a triggered, hardware-timed buffered acquisition (arguments `n_samples`,
    /// `sample_rate`, `trigger`) of `n_samples` samples at (at least) `sample_rate` Hz, started
    /// by `trigger`: the fast path of a raster line, where the
    /// stage sweeps under its controller's clock and the controller's trigger output starts the
    /// digitiser. Returns what the device will actually record (digitisers have fixed rate
    /// steps). Digitisers without a triggered buffer keep the default: an error saying so.
    fn arm_buffered(&mut self, _: usize, _: f64, _: Trigger) -> Result<BufferedArm, DeviceError> {
        Err(no_buffer(self.name(), "arm_buffered"))
    }
    /// Wait (at most `timeout` for the trigger, then the acquisition time) and read the
    /// acquisition armed by [`arm_buffered`](Self::arm_buffered). A trigger that never comes is
    /// an error naming the device, the trigger-state query and its last reply; the device's
    /// acquisition is stopped first.
    fn read_buffered(
        &mut self,
        timeout: std::time::Duration,
    ) -> Result<BufferedTrace, DeviceError> {
        let _ = timeout;
        Err(no_buffer(self.name(), "read_buffered"))
    }
    /// Stop an armed buffered acquisition (Ctrl-C, a fault elsewhere). Nothing to do by default.
    fn stop_buffered(&mut self) -> Result<(), DeviceError> {
        Ok(())
    }
    /// Wall time a read takes beyond its samples' n / rate (the link, the device's reply), s:
    /// the running mean of the reads so far, for the scan ETA; 0 when unknown.
    fn overhead_s(&self) -> f64 {
        0.0
    }
    /// As [`Stage::link_costs`].
    fn link_costs(&mut self) -> link::LinkCosts {
        Vec::new()
    }
}

fn no_buffer(device: String, call: &str) -> DeviceError {
    DeviceError::Other {
        device,
        detail: format!(
            "{call}: this digitiser has no triggered buffer (a Red Pitaya, `[qpd] backend = \"redpitaya\"`, has one)"
        ),
    }
}

/// What starts a buffered acquisition ([`Qpd::arm_buffered`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Trigger {
    /// At once, when armed (software trigger).
    Now,
    /// A rising edge on the digitiser's external trigger input (a controller's trigger output).
    ExternalRising,
    /// A falling edge on the external trigger input.
    ExternalFalling,
}

/// What an armed buffered acquisition will record.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BufferedArm {
    /// Samples per channel recorded from the trigger on.
    pub n_samples: usize,
    /// Actual sample rate, Hz (≥ the rate asked for, when the device can).
    pub sample_rate: f64,
}

/// A triggered buffered acquisition: samples of Sx, Sy, Sz (signal units, calibrated as point
/// reads are) and their time base. Sample `i` was taken `t0_s + i · dt_s` seconds after the
/// trigger.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BufferedTrace {
    /// Time of the first sample after the trigger, s.
    pub t0_s: f64,
    /// Sample interval, s.
    pub dt_s: f64,
    pub sx: Vec<f64>,
    pub sy: Vec<f64>,
    /// Zeros when the digitiser has no input wired to the sum signal (see `sz_measured`).
    pub sz: Vec<f64>,
    /// False when Sz was not digitised (a 2-input board with Sx and Sy wired).
    pub sz_measured: bool,
    /// Per sample, which signals' inputs were at or beyond the rail ([`range::clip_bits`]);
    /// empty when no sample was (or the range is unknown).
    pub clipped: Vec<u8>,
}

impl BufferedTrace {
    /// Samples per channel.
    pub fn len(&self) -> usize {
        self.sx.len()
    }
    pub fn is_empty(&self) -> bool {
        self.sx.is_empty()
    }
    /// Time of sample `i` after the trigger, s.
    pub fn time(&self, i: usize) -> f64 {
        self.t0_s + i as f64 * self.dt_s
    }
}

/// Wall-clock time for real hardware.
#[derive(Debug)]
pub struct WallClock {
    start: std::time::Instant,
}

impl Default for WallClock {
    fn default() -> Self {
        Self {
            start: std::time::Instant::now(),
        }
    }
}

impl Clock for WallClock {
    fn now(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }
    fn wait(&self, seconds: f64) {
        if seconds > 0.0 && seconds.is_finite() {
            std::thread::sleep(std::time::Duration::from_secs_f64(seconds));
        }
    }
    fn is_virtual(&self) -> bool {
        false
    }
}

/// Simulated time: `wait` advances the counter instantly, or, paced, also sleeps `pace` wall
/// seconds per simulated second (1 = real time: the simulator then runs at a real instrument's
/// speed, for demonstrations and the live view's tests).
#[derive(Debug, Default)]
pub struct VirtualClock {
    // seconds stored as f64 bits
    t: std::sync::atomic::AtomicU64,
    // wall seconds per simulated second, as f64 bits (0: no sleeping)
    pace: std::sync::atomic::AtomicU64,
}

impl VirtualClock {
    /// The pace of a new clock: 0, no sleeping (as fast as the simulator computes).
    pub const DEFAULT_PACE: f64 = 0.0;

    pub fn new() -> Self {
        Self {
            t: std::sync::atomic::AtomicU64::new(0f64.to_bits()),
            pace: std::sync::atomic::AtomicU64::new(Self::DEFAULT_PACE.to_bits()),
        }
    }

    /// Wall seconds each simulated second costs from now on (0: none; negative or non-finite
    /// values count as 0).
    pub fn set_pace(&self, pace: f64) {
        let p = if pace.is_finite() && pace > 0.0 {
            pace
        } else {
            0.0
        };
        self.pace
            .store(p.to_bits(), std::sync::atomic::Ordering::SeqCst);
    }

    /// The pace set by [`set_pace`](Self::set_pace).
    pub fn pace(&self) -> f64 {
        f64::from_bits(self.pace.load(std::sync::atomic::Ordering::SeqCst))
    }
}

impl Clock for VirtualClock {
    fn now(&self) -> f64 {
        f64::from_bits(self.t.load(std::sync::atomic::Ordering::SeqCst))
    }
    fn wait(&self, seconds: f64) {
        if !(seconds > 0.0 && seconds.is_finite()) {
            return;
        }
        use std::sync::atomic::Ordering::SeqCst;
        let _ = self.t.fetch_update(SeqCst, SeqCst, |b| {
            Some((f64::from_bits(b) + seconds).to_bits())
        });
        let pace = self.pace();
        if pace > 0.0 {
            std::thread::sleep(std::time::Duration::from_secs_f64(seconds * pace));
        }
    }
    fn is_virtual(&self) -> bool {
        true
    }
}

/// Everything the scan engine drives: a stage, a QPD and the clock their waits advance.
/// Built by `connect` from the config (simulated by default).
pub struct Instrument {
    pub stage: Box<dyn Stage>,
    pub qpd: Box<dyn Qpd>,
    pub clock: std::sync::Arc<dyn Clock>,
    /// Settle time after each move (s), waited on `clock`.
    pub settle_s: f64,
    /// Short description for `status()` and scan metadata (backend names, ports).
    pub description: serde_json::Value,
}

impl Instrument {
    /// Move and wait the settle time.
    pub fn move_settle(&mut self, target: Pos) -> Result<(), DeviceError> {
        self.stage.move_to(target)?;
        self.clock.wait(self.settle_s);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn virtual_clock_advances_without_sleeping() {
        let c = VirtualClock::new();
        let t0 = std::time::Instant::now();
        c.wait(3600.0);
        c.wait(0.5);
        c.wait(f64::NAN); // ignored, never poisons time
        assert_eq!(c.now(), 3600.5);
        assert!(t0.elapsed().as_secs_f64() < 0.5);
    }

    #[test]
    fn paced_clock_sleeps_its_pace() {
        let c = VirtualClock::new();
        c.set_pace(0.5);
        let t0 = std::time::Instant::now();
        c.wait(0.2);
        let wall = t0.elapsed().as_secs_f64();
        assert_eq!(c.now(), 0.2);
        assert!(
            wall >= 0.1,
            "slept {wall} s, pace 0.5 × 0.2 s asks for 0.1 s"
        );
        c.set_pace(f64::NAN);
        assert_eq!(c.pace(), 0.0);
    }
}
