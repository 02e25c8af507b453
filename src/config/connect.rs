//! Build an [`Instrument`] from the config: simulated, or the stage and the QPD its tables
//! name, each opened by its device family (`instrument::registry`, the family's `config.rs`). Also computes the limits in force (`[safety]` soft limits ∩ the travel range
//! the stage reports, with the step and speed limits), which `acquire/` enforces.

use super::{err, Config, ConfigError};
use crate::acquire::SoftLimits;
use crate::instrument::family::{OpenError, Opened};
use crate::instrument::registry;
use crate::instrument::{gcs::GCS, redpitaya::REDPITAYA, scpi::SCPI, sim::SIM};
use crate::instrument::{DeviceError, Instrument, Qpd, Stage, WallClock};
use serde_json::json;
use std::sync::Arc;

/// A connected instrument and the limits in force for it.
pub struct Connected {
    pub instrument: Instrument,
    /// Soft limits ∩ travel range, max step and speed (µm, µm/s).
    pub limits: SoftLimits,
}

/// Why `connect` failed.
#[derive(Debug, thiserror::Error)]
pub enum ConnectError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// The simulated instrument could not be built.
    #[error("simulated instrument: {0}")]
    Sim(anyhow::Error),
}

/// Connect what the config names.
///
/// - `sim`: `make_sim(cfg)` builds the simulated instrument (the caller owns the scene and
///   optics; it should use `cfg.stage.settle_s`).
/// - `gcs` + `scpi`: open the ports (one or several stage controllers, serial or TCP),
///   identify the devices (`*IDN?`), check the configured axes against `SAI?`, read `SVO?` and
///   `MOV?`, the travel range (`TMN?`/`TMX?`) and the sample rate. The clock is the wall clock.
///
/// In both cases the stage's travel range is then intersected with the `[safety]` soft
/// limits, and only when they fit is the stage switched on (`Stage::enable`: PI `SVO` for the
/// axes found off) and the speed limit sent (`VEL`): a connect refused for its limits leaves
/// the controller as it was found. A failure names the device and what it said; a half-opened
/// set of ports is closed again.
pub fn connect(
    cfg: &Config,
    make_sim: impl FnOnce(&Config) -> anyhow::Result<Instrument>,
) -> Result<Connected, ConnectError> {
    cfg.validate().map_err(|mut e| {
        if e.origin.is_empty() {
            e.origin = "config".into();
        }
        e
    })?;
    let mut instrument = match (cfg.stage.backend, cfg.qpd.backend) {
        (SIM, SIM) => make_sim(cfg).map_err(ConnectError::Sim)?,
        _ => connect_hardware(cfg)?,
    };
    let travel = instrument.stage.travel_range()?;
    let limits = cfg
        .soft_limits()
        .within_travel(travel)
        .map_err(|e| ConfigError {
            origin: "bfpscope.toml".into(),
            key: format!("safety.soft_limits.{}", e.axis),
            line: None,
            message: e.message,
        })?;
    instrument.stage.enable()?;
    // positioning moves respect the [safety] speed limit too, not only scan steps
    if let Some(v) = limits.max_speed_um_s {
        instrument.stage.set_velocity(v)?;
    }
    if let serde_json::Value::Object(m) = &mut instrument.description {
        m.insert("travel_um".into(), json!(travel));
        m.insert(
            "limits".into(),
            serde_json::to_value(limits).unwrap_or_default(),
        );
    }
    record_gauge(&mut instrument);
    Ok(Connected { instrument, limits })
}

/// Record the strain gauges' zero state (stages with gauges: the KPZ101 cubes) in the
/// instrument description, which every scan's metadata carries (`instrument.stage.
/// gauge_zeroed = {x, y, z}`), and a warning per gauge not zeroed (`instrument.warnings`,
/// shown by `connect()`). Called at connect and after `zero_gauge()`.
pub fn record_gauge(instrument: &mut Instrument) {
    let Some(z) = instrument.stage.gauge().map(|g| g.gauge_zeroed()) else {
        return;
    };
    let name = instrument.stage.name();
    let serde_json::Value::Object(m) = &mut instrument.description else {
        return;
    };
    if let Some(serde_json::Value::Object(st)) = m.get_mut("stage") {
        st.insert(
            "gauge_zeroed".into(),
            json!({ "x": z[0], "y": z[1], "z": z[2] }),
        );
    }
    let not: Vec<&str> = ["x", "y", "z"]
        .into_iter()
        .zip(z)
        .filter(|(_, ok)| !ok)
        .map(|(a, _)| a)
        .collect();
    let mut warnings: Vec<serde_json::Value> = match m.get("warnings") {
        Some(serde_json::Value::Array(w)) => w
            .iter()
            .filter(|w| !w.as_str().is_some_and(|t| t.contains("strain gauge")))
            .cloned()
            .collect(),
        _ => Vec::new(),
    };
    if !not.is_empty() {
        warnings.push(json!(format!(
            "{name}: the strain gauge of {} is not zeroed (status bit 0x10 of \
             MGMSG_PZ_GET_PZSTATUSUPDATE clear): closed-loop positions carry the gauge's offset. \
             Zero it with zero_gauge() (the actuators go to 0 V, their zero, and hold there) or \
             set [stage] zero_at_connect = true",
            not.join(", ")
        )));
    }
    if warnings.is_empty() {
        m.remove("warnings");
    } else {
        m.insert("warnings".into(), serde_json::Value::Array(warnings));
    }
}

/// Open what the config's `[stage]` and `[qpd]` name, each through its family's section
/// (`instrument::registry`): a family that ties the two (the NI raster) opens both; else the
/// stage, then the QPD (if the QPD fails, the stage is dropped and its ports closed).
fn connect_hardware(cfg: &Config) -> Result<Instrument, ConnectError> {
    let tables = cfg.tables();
    let stage_family = registry::by_stage(cfg.stage.backend.as_str());
    let qpd_family = registry::by_qpd(cfg.qpd.backend.as_str());
    for f in [stage_family, qpd_family].into_iter().flatten() {
        if let Some(pair) = f.section.open_pair {
            if let Some((stage, qpd)) = pair(&tables).map_err(open_error)? {
                return Ok(hardware_instrument(cfg, stage, qpd));
            }
        }
    }
    let stage = stage_family
        .and_then(|f| f.section.open_stage)
        .ok_or_else(|| not_from_config("stage.backend", cfg.stage.backend.as_str()))?;
    let stage = stage(&tables).map_err(open_error)?;
    let qpd = qpd_family
        .and_then(|f| f.section.open_qpd)
        .ok_or_else(|| not_from_config("qpd.backend", cfg.qpd.backend.as_str()))?;
    let qpd = qpd(&tables).map_err(open_error)?;
    Ok(hardware_instrument(cfg, stage, qpd))
}

/// A backend whose family does not open that device from the config's tables.
fn not_from_config(key: &str, backend: &str) -> ConnectError {
    err(
        key,
        format!("\"{backend}\": its family does not open this device from bfpscope.toml"),
    )
    .into()
}

/// A family's opening error as `connect`'s.
fn open_error(e: OpenError) -> ConnectError {
    match e {
        OpenError::Table(e) => err(&e.key, e.message).into(),
        OpenError::Device(e) => e.into(),
    }
}

/// A connected hardware stage and QPD as the session's instrument: the wall clock, the
/// configured settle time, and the description scans record.
fn hardware_instrument(
    cfg: &Config,
    stage: Opened<Box<dyn Stage>>,
    qpd: Opened<Box<dyn Qpd>>,
) -> Instrument {
    Instrument {
        stage: stage.device,
        qpd: qpd.device,
        clock: Arc::new(WallClock::default()),
        settle_s: cfg.stage.settle_s,
        description: json!({
            "backend": crate::instrument::family::HARDWARE,
            "stage": stage.description,
            "qpd": qpd.description,
            "settle_s": cfg.stage.settle_s,
        }),
    }
}

/// An emulated instrument connected through the real drivers (`connect_emulated`): the
/// connection and the two emulators it talks to (keep them alive as long as the connection).
pub struct Emulated {
    pub connected: Connected,
    pub stage: crate::instrument::emulator::Emulator,
    pub qpd: crate::instrument::emulator::Emulator,
}

/// An emulator's detector noise (V rms): a finite number ≥ 0.
fn check_noise_v(noise_v: f64) -> Result<(), ConnectError> {
    if noise_v.is_finite() && noise_v >= 0.0 {
        return Ok(());
    }
    Err(ConnectError::Config(ConfigError {
        origin: "connect".into(),
        key: "noise_v".into(),
        line: None,
        message: format!("{noise_v} V: must be a finite number ≥ 0"),
    }))
}

/// Start a GCS stage emulator and a SCPI QPD emulator on pseudo-terminals in this process and
/// connect the real drivers to them: the hardware path without hardware.
///
/// The stage has the simulator's travel range and move time (`StageEmulatorConfig::like_sim`,
/// parked at the origin); the QPD answers with the ideal signal of `renderer`'s scene at the
/// emulated stage position (`sim_signal_source`), 1 V per signal unit, plus white detector
/// noise of `noise_v` volts rms per sample, in real time (a read of n samples takes n / rate).
/// From `base` only the `[safety]` table and `stage.settle_s` are used (its ports and serial
/// settings belong to the real hardware). The description's `backend` is `"emulated"`.
pub fn connect_emulated(
    renderer: Arc<crate::instrument::sim::Renderer>,
    sim: &crate::instrument::sim::SimConfig,
    base: &Config,
    noise_v: f64,
) -> Result<Emulated, ConnectError> {
    use crate::instrument::emulator::{
        sim_signal_source, start_pair, QpdEmulatorConfig, StageEmulatorConfig,
    };
    check_noise_v(noise_v)?;
    let qcfg = QpdEmulatorConfig {
        sample_rate_hz: sim.sample_rate,
        noise_v: [noise_v; 3],
        ..QpdEmulatorConfig::default()
    };
    let (stage, qpd) = start_pair(
        StageEmulatorConfig::like_sim(sim),
        qcfg,
        sim_signal_source(renderer),
    )
    .map_err(|e| DeviceError::Other {
        device: "emulator".into(),
        detail: format!("cannot start the emulators on pseudo-terminals: {e}"),
    })?;
    let mut cfg = emulated_stage_config(base, stage.path());
    cfg.qpd.backend = SCPI;
    cfg.qpd.port = Some(qpd.path().to_string());
    let emulators = json!({
        "stage": stage.path(),
        "qpd": qpd.path(),
        "noise_v": noise_v,
        "signal": "simulator (ideal signal of the scene) at the emulated stage position",
    });
    finish_emulated(&cfg, stage, qpd, emulators)
}

/// The config of an emulated GCS stage at `path`: `base`'s `[safety]` and settle time, the
/// emulator polled every millisecond (its replies are local).
fn emulated_stage_config(base: &Config, path: &str) -> Config {
    let mut cfg = Config {
        safety: base.safety,
        ..Config::default()
    };
    cfg.stage.backend = GCS;
    cfg.stage.port = Some(path.to_string());
    cfg.stage.settle_s = base.stage.settle_s;
    cfg.stage.poll_ms = Some(1);
    cfg
}

/// Connect through the real drivers to the emulators `cfg` names, and say so in the
/// instrument's description (`backend: "emulated"`, what each emulator is).
fn finish_emulated(
    cfg: &Config,
    stage: crate::instrument::emulator::Emulator,
    qpd: crate::instrument::emulator::Emulator,
    emulators: serde_json::Value,
) -> Result<Emulated, ConnectError> {
    let mut connected = connect(cfg, |_| {
        Err(anyhow::anyhow!(
            "a hardware config does not build the simulator"
        ))
    })?;
    if let serde_json::Value::Object(m) = &mut connected.instrument.description {
        m.insert(
            "backend".into(),
            json!(crate::instrument::emulator::FAMILY.backend),
        );
        m.insert("emulators".into(), emulators);
    }
    Ok(Emulated {
        connected,
        stage,
        qpd,
    })
}

/// How [`connect_emulated_redpitaya`] serves the GCS stage emulator.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum EmulatedStageLink {
    /// A pseudo-terminal, as a USB-serial controller (no baud limit).
    #[default]
    Pty,
    /// A loopback TCP port, as a controller's GCS port 50000.
    Tcp,
}

/// As [`connect_emulated`], with a Red Pitaya STEMlab 125-14 4-input emulator in place of the
/// SCPI QPD: the instrument of a hardware-timed raster. The stage's trigger output OUT1 is
/// wired to the board's external trigger (`[stage] trigger_line = 1`), the stage publishes the
/// path of a running wave and the board samples it (each sample carries the scene's signal at
/// the stage position at its own time). Sx, Sy, Sz → IN1, IN2, IN3, 1 V per signal unit (IN3
/// 0.5 V + Sz: the total, so that the board sees light; the calibration's offset takes the
/// 0.5 V off), `noise_v` volts rms per ADC sample (125 MS/s; a decimated sample averages `dec` of them).
/// The stage is served on a pseudo-terminal or a loopback TCP port (`link`), the board on a
/// loopback TCP port. The description's `backend` is `"emulated"`.
pub fn connect_emulated_redpitaya(
    renderer: Arc<crate::instrument::sim::Renderer>,
    sim: &crate::instrument::sim::SimConfig,
    base: &Config,
    noise_v: f64,
    link: EmulatedStageLink,
) -> Result<Emulated, ConnectError> {
    use crate::instrument::emulator::{
        shared_position, sim_signal_source, start_redpitaya_emulator, start_stage_emulator,
        start_stage_emulator_tcp, RedPitayaEmulatorConfig, StageEmulatorConfig, StagePath,
    };
    check_noise_v(noise_v)?;
    let emu_err = |what: &str, e: std::io::Error| DeviceError::Other {
        device: "emulator".into(),
        detail: format!("cannot start the {what} emulator: {e}"),
    };
    let mut stage_cfg = StageEmulatorConfig::like_sim(sim);
    let pos = shared_position(stage_cfg.start);
    let path = StagePath::new();
    let (qpd, ext) = start_redpitaya_emulator(
        RedPitayaEmulatorConfig {
            noise_v,
            // the sum input carries the detector's total, 0.5 V with no sample (Sz = 0; mid-range
            // of the ±1 V inputs): a board reading 0 V there sees no light (a dark pixel); the
            // calibration's offset takes it off
            offset_v: [0.0, 0.0, 0.5, 0.0],
            path: Some(path.clone()),
            along: Some(crate::instrument::emulator::sim_signal_along(
                renderer.clone(),
            )),
            ..RedPitayaEmulatorConfig::four_inputs()
        },
        pos.clone(),
        sim_signal_source(renderer),
        "127.0.0.1:0",
    )
    .map_err(|e| emu_err("Red Pitaya", e))?;
    stage_cfg.wave.trigger_out[0] = Some(ext);
    stage_cfg.wave.path = Some(path);
    let stage = match link {
        EmulatedStageLink::Pty => start_stage_emulator(stage_cfg, pos),
        EmulatedStageLink::Tcp => start_stage_emulator_tcp(stage_cfg, pos, "127.0.0.1:0"),
    }
    .map_err(|e| emu_err("GCS stage", e))?;
    let hostport = qpd.path().trim_start_matches("tcp://").to_string();
    let (host, port) = hostport
        .rsplit_once(':')
        .map(|(h, p)| (h.to_string(), p.to_string()))
        .unwrap_or((hostport.clone(), "5000".into()));
    let mut cfg = emulated_stage_config(base, stage.path());
    cfg.stage.trigger_line = Some(1);
    cfg.qpd.backend = REDPITAYA;
    cfg.qpd.host = Some(host);
    cfg.qpd.port = Some(port);
    cfg.qpd.channels = super::QpdChannels::Inputs(crate::instrument::redpitaya::ChannelMap {
        sx: 1,
        sy: 2,
        sz: Some(3),
    });
    cfg.qpd.sample_rate_hz = sim.sample_rate;
    cfg.qpd.calibration.offset_v = [0.0, 0.0, 0.5];
    let emulators = json!({
        "stage": stage.path(),
        "qpd": qpd.path(),
        "qpd_model": "Red Pitaya STEMlab 125-14 4-input",
        "trigger": "stage OUT1 → board DIO0_P (EXT trigger)",
        "noise_v": noise_v,
        "signal": "simulator (ideal signal of the scene) at the emulated stage position, followed sample by sample during a wave",
    });
    finish_emulated(&cfg, stage, qpd, emulators)
}
