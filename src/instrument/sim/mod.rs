//! The simulated instrument: a stage and a QPD that image a `Scene` through the render pipeline,
//! on a virtual clock (settle and dwell advance simulated time, not wall time).

pub mod detector;
pub mod domain;
pub mod render;
pub mod scene;

use super::{Clock, DeviceError, Instrument, Pos, Qpd, QpdReading, Stage, VirtualClock};
use crate::data::{Image, Scan};
use crate::optics::params::OpticsError;
use crate::optics::template::TemplateSpec;
use crate::optics::{OpticsArg, ValidOptics};
use domain::{DomainCheck, DomainMemo};
use ndarray::Array2;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
pub use render::{Renderer, StageInfo};
pub use scene::Scene;
use std::sync::{Arc, Mutex, MutexGuard};

/// Lock a mutex, recovering the data if a panic elsewhere poisoned it (a simulator state is
/// plain data: every update leaves it consistent).
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Simulated hardware settings.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SimConfig {
    /// Travel range per axis, µm (a PDQ375-like piezo stage centred on 0).
    pub travel: [(f64, f64); 3],
    /// QPD digitiser sampling rate, Hz.
    pub sample_rate: f64,
    /// Time a move takes before the stage is on target, s.
    pub move_time_s: f64,
    /// Servo cycle of the simulated controller's wave generator and data recorder, s.
    pub servo_cycle_s: f64,
    /// Most points of one wave table, and of one record table.
    pub wave_points: usize,
    pub record_points: usize,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            travel: [(-37.5, 37.5), (-37.5, 37.5), (-25.0, 25.0)],
            sample_rate: 1e5,
            move_time_s: 0.002,
            // as a PI E-727: 50 µs servo cycle, 2^16-point wave and record tables
            servo_cycle_s: 50e-6,
            wave_points: 65_536,
            record_points: 65_536,
        }
    }
}

struct SimState {
    renderer: Arc<Renderer>,
    commanded: Pos,
    rng: ChaCha8Rng,
    /// random-walk part of the drift, µm, and the time it was last advanced
    walk: [f64; 3],
    walk_t: f64,
    /// The hardware-timed line configured or played last (raster scans).
    line: Option<SimLine>,
    /// The digitiser's armed buffered acquisition: samples, rate (Hz), servo samples averaged
    /// per digitiser sample.
    armed: Option<(usize, f64, usize)>,
}

/// A hardware-timed line in the simulator: the wave's target per servo cycle and the stage's
/// position following it through the `stage_bandwidth` lag (none without that effect).
struct SimLine {
    sweep: super::line::LineSweep,
    targets: Vec<f64>,
    x: Vec<f64>,
    /// Where the other axes stand (µm).
    base: Pos,
    /// Instrument time of the wave's start (`None`: configured, not started).
    t_start: Option<f64>,
    /// Servo cycles played (fewer than the wave after a stop).
    played: usize,
}

impl SimLine {
    /// The axis' position `t` s after the wave's start, interpolated between servo cycles; it
    /// holds the last position played after the wave (or a stop).
    fn x_at(&self, t: f64) -> f64 {
        let dt = self.sweep.servo_cycle_s;
        let last = self.played.max(1) - 1;
        let u = (t / dt).max(0.0);
        let i = (u.floor() as usize).min(last);
        if i >= last {
            return self.x[last];
        }
        let f = u - i as f64;
        self.x[i] + f * (self.x[i + 1] - self.x[i])
    }
}

/// Shared core of the simulated stage and QPD.
#[derive(Clone)]
pub struct SimCore {
    state: Arc<Mutex<SimState>>,
    /// The point dipole's domain results of this session (bounded), for every scene set.
    domain: Arc<Mutex<DomainMemo>>,
    pub clock: Arc<VirtualClock>,
    pub cfg: SimConfig,
}

impl SimCore {
    pub fn new(
        optics: &impl OpticsArg,
        scene: &Scene,
        cfg: SimConfig,
    ) -> Result<Self, OpticsError> {
        let mut memo = DomainMemo::default();
        let optics = optics.valid()?;
        let optics: &ValidOptics = &optics;
        let domain = DomainCheck::run(optics, scene, &mut memo);
        let renderer = Arc::new(Renderer::new(
            optics,
            scene,
            TemplateSpec::default(),
            &domain,
        )?);
        let core = Self::from_renderer(renderer, cfg);
        *lock(&core.domain) = memo;
        Ok(core)
    }

    pub fn from_renderer(renderer: Arc<Renderer>, cfg: SimConfig) -> Self {
        let seed = renderer.scene.seed;
        Self {
            state: Arc::new(Mutex::new(SimState {
                renderer,
                commanded: [0.0; 3],
                rng: ChaCha8Rng::seed_from_u64(seed),
                walk: [0.0; 3],
                walk_t: 0.0,
                line: None,
                armed: None,
            })),
            domain: Arc::new(Mutex::new(DomainMemo::default())),
            clock: Arc::new(VirtualClock::new()),
            cfg,
        }
    }

    pub fn renderer(&self) -> Arc<Renderer> {
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .renderer
            .clone()
    }

    /// Replace the scene (keeps position and clock).
    pub fn set_scene(&self, optics: &ValidOptics, scene: &Scene) -> Result<(), OpticsError> {
        let domain = DomainCheck::run(optics, scene, &mut lock(&self.domain));
        let r = Arc::new(Renderer::new(
            optics,
            scene,
            TemplateSpec::default(),
            &domain,
        )?);
        let mut st = self
            .state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        st.rng = ChaCha8Rng::seed_from_u64(scene.seed);
        st.renderer = r;
        Ok(())
    }

    /// The stage position the sample really has at time t: commanded + drift.
    fn actual(st: &mut SimState, t: f64) -> Pos {
        let mut p = st.commanded;
        if let Some(d) = st.renderer.scene.effects.drift {
            let dt = t - st.walk_t;
            if dt > 0.0 {
                let s = d.random_walk_nm_sqrt_s * 1e-3 * dt.sqrt();
                for c in 0..3 {
                    st.walk[c] += s * <StandardNormal as Distribution<f64>>::sample(
                        &StandardNormal,
                        &mut st.rng,
                    );
                }
                st.walk_t = t;
            }
            for c in 0..3 {
                p[c] += d.velocity_nm_s[c] * 1e-3 * t + st.walk[c];
            }
        }
        p
    }

    /// An `Instrument` (stage + QPD + virtual clock) over this core.
    pub fn instrument(&self, settle_s: f64) -> Instrument {
        Instrument {
            stage: Box::new(SimStage(self.clone())),
            qpd: Box::new(SimQpd(self.clone())),
            clock: self.clock.clone(),
            settle_s,
            description: serde_json::json!({
                "backend": "sim",
                "stage": "simulated piezo stage",
                "qpd": format!("simulated QPD at {} Hz", self.cfg.sample_rate),
                "travel_um": self.cfg.travel,
            }),
        }
    }
}

pub struct SimStage(pub SimCore);
pub struct SimQpd(pub SimCore);

impl Stage for SimStage {
    fn name(&self) -> String {
        "sim stage".into()
    }
    fn position(&mut self) -> Result<Pos, DeviceError> {
        Ok(self
            .0
            .state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .commanded)
    }
    fn move_to(&mut self, target: Pos) -> Result<(), DeviceError> {
        for (c, &v) in target.iter().enumerate() {
            let (lo, hi) = self.0.cfg.travel[c];
            if !(v >= lo && v <= hi) {
                // what a real controller does (GCS error 7); acquire/ refuses such moves first
                return Err(DeviceError::Controller {
                    device: self.name(),
                    command: format!("MOV {} {v}", super::AXES[c]),
                    code: 7,
                    message: format!("Position out of limits ({lo} … {hi} µm)"),
                });
            }
        }
        self.0
            .state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .commanded = target;
        self.0.clock.wait(self.0.cfg.move_time_s);
        Ok(())
    }
    fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError> {
        Ok(self.0.cfg.travel)
    }
    fn stop(&mut self) -> Result<(), DeviceError> {
        Ok(())
    }
    fn move_time_s(&self) -> f64 {
        self.0.cfg.move_time_s
    }

    super::stage_capabilities!(Lines);
}

/// The simulated wave generator and recorder: hardware-timed lines on the virtual clock.
impl super::LineScan for SimStage {
    fn line_timing(&mut self) -> Result<Option<super::line::LineTiming>, DeviceError> {
        Ok(Some(super::line::LineTiming {
            servo_cycle_s: self.0.cfg.servo_cycle_s,
            max_wave_points: self.0.cfg.wave_points,
            max_record_points: self.0.cfg.record_points,
            trigger_line: None,
        }))
    }
    fn configure_line(&mut self, s: &super::line::LineSweep) -> Result<(), DeviceError> {
        let (lo, hi) = self.0.cfg.travel[s.axis.min(2)];
        for v in [s.from_um, s.to_um] {
            if !(v >= lo && v <= hi) {
                return Err(DeviceError::Controller {
                    device: self.name(),
                    command: format!("WAV 1 X LIN … {v}"),
                    code: 7,
                    message: format!("Position out of limits ({lo} … {hi} µm)"),
                });
            }
        }
        if s.points > self.0.cfg.wave_points || s.points < 2 || s.rate == 0 {
            return Err(self.line_error(
                "WAV",
                format!(
                    "a wave of {} points at rate {}: the table holds 2 … {}",
                    s.points, s.rate, self.0.cfg.wave_points
                ),
            ));
        }
        let mut st = lock(&self.0.state);
        let tau = st
            .renderer
            .scene
            .effects
            .stage_bandwidth
            .map_or(0.0, |b| b.tau_s());
        let targets = s.targets_per_cycle();
        let x = super::line::lagged(&targets, s.servo_cycle_s, tau);
        let base = st.commanded;
        st.line = Some(SimLine {
            sweep: s.clone(),
            played: targets.len(),
            targets,
            x,
            base,
            t_start: None,
        });
        Ok(())
    }
    fn start_line(&mut self, _s: &super::line::LineSweep) -> Result<(), DeviceError> {
        let now = self.0.clock.now();
        let mut st = lock(&self.0.state);
        let here = st.commanded;
        match st.line.as_mut() {
            Some(l) => {
                // the wave plays again from wherever the other axes now stand
                l.t_start = Some(now);
                l.base = here;
                l.played = l.targets.len();
                Ok(())
            }
            None => Err(self.line_error("WGO 1 1", "no line configured".into())),
        }
    }
    fn wait_line(
        &mut self,
        s: &super::line::LineSweep,
        abort: &std::sync::atomic::AtomicBool,
    ) -> Result<bool, DeviceError> {
        if abort.load(std::sync::atomic::Ordering::SeqCst) {
            // stopped at its start: nothing played
            if let Some(l) = lock(&self.0.state).line.as_mut() {
                l.played = 1;
            }
            self.stop_line(s)?;
            return Ok(false);
        }
        self.0.clock.wait(s.duration_s());
        let mut st = lock(&self.0.state);
        if let Some(l) = st.line.as_ref() {
            let mut p = l.base;
            p[l.sweep.axis] = *l.targets.last().unwrap_or(&p[l.sweep.axis]);
            st.commanded = p;
        }
        Ok(true)
    }
    fn read_line_record(
        &mut self,
        _s: &super::line::LineSweep,
    ) -> Result<super::line::SweepRecord, DeviceError> {
        let st = lock(&self.0.state);
        let Some(l) = st.line.as_ref() else {
            return Err(self.line_error("DRR? 1 0 1 2", "no line played".into()));
        };
        let r = l.sweep.record_rate.max(1) as usize;
        let idx = (0..l.played).step_by(r);
        Ok(super::line::SweepRecord {
            sample_time_s: r as f64 * l.sweep.servo_cycle_s,
            target_um: idx.clone().map(|j| l.targets[j]).collect(),
            position_um: idx.map(|j| l.x[j]).collect(),
        })
    }
    fn stop_line(&mut self, _s: &super::line::LineSweep) -> Result<(), DeviceError> {
        let mut st = lock(&self.0.state);
        if let Some(l) = st.line.as_ref() {
            let mut p = l.base;
            p[l.sweep.axis] = l.x[l.played.max(1) - 1];
            st.commanded = p;
        }
        Ok(())
    }
}

impl SimStage {
    fn line_error(&self, command: &str, detail: String) -> DeviceError {
        DeviceError::Other {
            device: self.name(),
            detail: format!("`{command}`: {detail}"),
        }
    }
}

impl Qpd for SimQpd {
    fn name(&self) -> String {
        "sim QPD".into()
    }
    fn sample_rate(&self) -> f64 {
        self.0.cfg.sample_rate
    }
    /// With the scene's `detector_range` effect: its range and sum floor (signal units).
    fn input_range(&self) -> Option<crate::instrument::range::InputRange> {
        lock(&self.0.state)
            .renderer
            .scene
            .effects
            .detector_range
            .as_ref()
            .map(detector::input_range)
    }
    fn metadata(&self) -> Option<serde_json::Value> {
        let st = self
            .0
            .state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let mut m = serde_json::json!({ "pipeline": st.renderer.stages() });
        if !st.renderer.notes.is_empty() {
            m["model_notes"] = serde_json::json!(st.renderer.notes);
        }
        Some(m)
    }
    fn read(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        if n == 0 {
            return Err(DeviceError::Other {
                device: self.name(),
                detail: "read: n = 0 samples; n must be ≥ 1".into(),
            });
        }
        let dur = n as f64 / self.0.cfg.sample_rate;
        let t_mid = self.0.clock.now() + 0.5 * dur;
        let mut st = self
            .0
            .state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let pos = SimCore::actual(&mut st, t_mid);
        let r = st.renderer.clone();
        let (v, sd) = r.render_point(pos, n, &mut st.rng);
        drop(st);
        let (v, clipped) = r.detect(v, sd, n);
        self.0.clock.wait(dur);
        Ok(QpdReading {
            sx: v[0],
            sy: v[1],
            sz: v[2],
            sx_std: sd[0],
            sy_std: sd[1],
            sz_std: sd[2],
            n,
            clipped,
        })
    }
    /// The simulated digitiser decimates as a Red Pitaya does: each buffered sample is the
    /// mean of `k = round(sample_rate / rate)` detector samples (at least 1), so a pixel of
    /// a raster line has the noise of a point read of the same dwell. Its trigger is the
    /// simulated stage's wave start.
    fn arm_buffered(
        &mut self,
        n_samples: usize,
        sample_rate: f64,
        _trigger: super::Trigger,
    ) -> Result<super::BufferedArm, DeviceError> {
        if n_samples == 0 || !(sample_rate.is_finite() && sample_rate > 0.0) {
            return Err(DeviceError::Other {
                device: self.name(),
                detail: format!(
                    "arm_buffered: {n_samples} samples at {sample_rate} Hz: need ≥ 1 sample and a finite rate > 0"
                ),
            });
        }
        let k = ((self.0.cfg.sample_rate / sample_rate).floor() as usize).max(1);
        let rate = self.0.cfg.sample_rate / k as f64;
        let n = ((n_samples as f64 * rate / sample_rate).ceil() as usize).max(1);
        lock(&self.0.state).armed = Some((n, rate, k));
        Ok(super::BufferedArm {
            n_samples: n,
            sample_rate: rate,
        })
    }
    fn read_buffered(
        &mut self,
        _timeout: std::time::Duration,
    ) -> Result<super::BufferedTrace, DeviceError> {
        let mut st = lock(&self.0.state);
        let Some((n, rate, k)) = st.armed.take() else {
            return Err(DeviceError::Other {
                device: self.name(),
                detail: "read_buffered: no acquisition armed".into(),
            });
        };
        let Some((t_start, axis, base)) = st
            .line
            .as_ref()
            .and_then(|l| l.t_start.map(|t| (t, l.sweep.axis, l.base)))
        else {
            return Err(DeviceError::Other {
                device: self.name(),
                detail: "read_buffered: the trigger never came (no line was started)".into(),
            });
        };
        let r = st.renderer.clone();
        let dt = 1.0 / rate;
        let mut tr = super::BufferedTrace {
            // sample i averages [i·dt, (i+1)·dt) after the trigger: its time is the middle
            t0_s: 0.5 * dt,
            dt_s: dt,
            sx: Vec::with_capacity(n),
            sy: Vec::with_capacity(n),
            sz: Vec::with_capacity(n),
            sz_measured: true,
            clipped: Vec::new(),
        };
        let commanded = st.commanded;
        for i in 0..n {
            let t = tr.t0_s + i as f64 * dt;
            let x = st.line.as_ref().map_or(base[axis], |l| l.x_at(t));
            let drifted = SimCore::actual(&mut st, t_start + t);
            let mut p = base;
            p[axis] = x;
            for c in 0..3 {
                p[c] += drifted[c] - commanded[c];
            }
            let (v, sd) = r.render_point(p, k, &mut st.rng);
            // a digitiser sample whose detector samples touched the rail is flagged
            let (v, hit) = r.detect(v, sd, k);
            if hit.iter().any(|&h| h > 0) {
                tr.clipped.resize(n, 0);
                tr.clipped[i] = crate::instrument::range::clip_bits(hit.map(|h| h > 0));
            }
            tr.sx.push(v[0]);
            tr.sy.push(v[1]);
            tr.sz.push(v[2]);
        }
        Ok(tr)
    }
}

/// Render an XY image of a scene directly (no stage, no clock): the ideal superposition over
/// the grid, plus the per-pixel effects in pixel order when the scene asks for them. Used by
/// `simulate(scene, grid)`, figure scripts and benchmarks.
pub fn render_xy(renderer: &Renderer, xs: &[f64], ys: &[f64], z: f64, n_samples: usize) -> Scan {
    let fx = &renderer.scene.effects;
    let per_pixel = fx.thermal_motion.is_some()
        || fx.drift.is_some()
        || fx.pointing_noise.is_some()
        || fx.cross_terms == Some(true)
        || fx.laser_power_noise.is_some()
        || fx.detector_noise.is_some()
        || fx.detector_range.is_some();
    let (nx, ny) = (xs.len(), ys.len());
    let mut ch = [
        Array2::<f64>::zeros((ny, nx)),
        Array2::<f64>::zeros((ny, nx)),
        Array2::<f64>::zeros((ny, nx)),
    ];
    let range = fx.detector_range.as_ref().map(detector::input_range);
    let mut clip = crate::data::clip::ClipTally::new(ys.len(), xs.len(), range);
    if per_pixel {
        let mut rng = ChaCha8Rng::seed_from_u64(renderer.scene.seed);
        let dt = n_samples as f64 / SimConfig::default().sample_rate;
        for (iy, &y) in ys.iter().enumerate() {
            for (ix, &x) in xs.iter().enumerate() {
                let mut p = [x, y, z];
                if let Some(d) = fx.drift {
                    let t = (iy * nx + ix) as f64 * dt;
                    for c in 0..3 {
                        p[c] += d.velocity_nm_s[c] * 1e-3 * t;
                    }
                }
                let (v, sd) = renderer.render_point(p, n_samples, &mut rng);
                let (v, hit) = renderer.detect(v, sd, n_samples);
                if hit.iter().any(|&h| h > 0) {
                    let k = hit.map(|h| u32::try_from(h).unwrap_or(u32::MAX));
                    clip.add(&[(iy, ix, k)]);
                }
                for c in 0..3 {
                    ch[c][[iy, ix]] = v[c];
                }
            }
        }
    } else {
        let out = renderer.render_grid_ideal(xs, ys, z);
        for c in 0..3 {
            ch[c] = Array2::from_shape_vec((ny, nx), out[c].clone()).expect("grid shape");
        }
    }
    let meta = serde_json::json!({
        "kind": "simulate",
        "z_um": z,
        "n_samples": n_samples,
        "optics": renderer.optics,
        "scene": renderer.scene,
        "pipeline": renderer.stages(),
    });
    let mut scan = Scan::complete(ch.map(|a| Image::new(a, xs.to_vec(), ys.to_vec())), meta);
    // the detector's clipped and dark pixels (the `detector_range` effect), said by the caller
    clip.finish(&mut scan, "simulate", &|_| {});
    scan
}

/// The simulated instrument: a scene rendered in the focused beam, on a virtual clock. (listed in `instrument::registry`).
/// The simulated instrument (scene + optics): `[stage]` and `[qpd]` backend.
pub const SIM: crate::instrument::family::Backend = crate::instrument::family::Backend("sim");

pub const FAMILY: crate::instrument::family::Family = crate::instrument::family::Family {
    stages: &[SIM.0],
    qpds: &[SIM.0],
    keys: &["scene", "pace"],
    help: crate::instrument::family::ConnectHelp {
        backend: "\"sim\"",
        about: "\"sim\": the simulated instrument.",
    },
    ..crate::instrument::family::Family::new("sim", "sim", crate::instrument::family::Open::Sim)
};
