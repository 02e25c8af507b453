//! Build an [`Instrument`] from the config: simulated, or a GCS stage and a SCPI QPD on
//! serial ports. Also computes the limits in force (`[safety]` soft limits ∩ the travel range
//! the stage reports, with the step and speed limits), which `acquire/` enforces.

use super::{err, Config, ConfigError};
use crate::acquire::SoftLimits;
use crate::instrument::gcs::split::GcsSplitStage;
use crate::instrument::gcs::GcsStage;
use crate::instrument::scpi::ScpiQpd;
use crate::instrument::{
    gcs::GCS, madlib::MADLIB, nidaqmx::NIDAQMX, redpitaya::REDPITAYA, scpi::SCPI, sim::SIM,
    thorlabs::KPA101, thorlabs::KPZ101,
};
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
    let Some(z) = instrument
        .stage
        .capabilities()
        .gauge
        .map(|g| g.gauge_zeroed())
    else {
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

fn connect_hardware(cfg: &Config) -> Result<Instrument, ConnectError> {
    if cfg.stage.backend == MADLIB || cfg.qpd.backend == NIDAQMX {
        return connect_bench(cfg);
    }
    if cfg.stage.backend == KPZ101 || cfg.qpd.backend == KPA101 {
        return connect_apt(cfg);
    }
    let qport = cfg.qpd.port.clone().unwrap_or_default();
    let controllers = cfg.gcs_controllers();
    // Opened read-only: nothing is switched on before `connect` has checked the limits.
    let (stage, parts): (Box<dyn crate::instrument::Stage>, Vec<serde_json::Value>) =
        if controllers.len() == 1 {
            let (port, o) = &controllers[0];
            let s = GcsStage::open_checked(port, cfg.stage.baud, o.clone())?;
            let d = controller_json(&s, port);
            (Box::new(s), vec![d])
        } else {
            let s = GcsSplitStage::open_checked(&controllers, cfg.stage.baud)?;
            let d = s
                .controllers()
                .iter()
                .zip(&controllers)
                .map(|(c, (port, _))| controller_json(c, port))
                .collect();
            (Box::new(s), d)
        };
    // If the QPD fails, `stage` is dropped here and its ports closed.
    let (qpd, qpd_desc): (Box<dyn crate::instrument::Qpd>, serde_json::Value) =
        if cfg.qpd.backend == REDPITAYA {
            open_redpitaya(cfg)?
        } else {
            let qpd = ScpiQpd::open(&qport, cfg.qpd.baud, cfg.scpi_options())?;
            let d = json!({
                "backend": "scpi",
                "name": crate::instrument::Qpd::name(&qpd),
                "port": qport,
                "baud": cfg.qpd.baud,
                "idn": qpd.idn(),
                "sample_rate_hz": crate::instrument::Qpd::sample_rate(&qpd),
                "calibration": cfg.qpd.calibration,
            });
            (Box::new(qpd), d)
        };
    let port = match &cfg.stage.ports {
        Some(p) => json!({ "x": p.x, "y": p.y, "z": p.z }),
        None => json!(cfg.stage.port.clone().unwrap_or_default()),
    };
    let stage_desc = json!({
        "backend": "gcs",
        "name": stage.name(),
        "port": port,
        "baud": cfg.stage.baud,
        "idn": parts.iter().map(|p| p["idn"].as_str().unwrap_or_default()).collect::<Vec<_>>().join(" + "),
        "axes": { "x": cfg.stage.axes.x, "y": cfg.stage.axes.y, "z": cfg.stage.axes.z },
        "units_per_um": cfg.stage.units_per_um,
        "controllers": parts,
    });
    Ok(hardware_instrument(cfg, stage, qpd, stage_desc, qpd_desc))
}

/// A connected hardware stage and QPD as the session's instrument: the wall clock, the
/// configured settle time, and the description scans record.
fn hardware_instrument(
    cfg: &Config,
    stage: Box<dyn Stage>,
    qpd: Box<dyn Qpd>,
    stage_desc: serde_json::Value,
    qpd_desc: serde_json::Value,
) -> Instrument {
    Instrument {
        stage,
        qpd,
        clock: Arc::new(WallClock::default()),
        settle_s: cfg.stage.settle_s,
        description: json!({
            "backend": crate::instrument::family::HARDWARE,
            "stage": stage_desc,
            "qpd": qpd_desc,
            "settle_s": cfg.stage.settle_s,
        }),
    }
}

/// The SCPI QPD digitiser on the config's port, with its description.
fn open_scpi(cfg: &Config) -> Result<(Box<dyn Qpd>, serde_json::Value), ConnectError> {
    let port = cfg.qpd.port.clone().unwrap_or_default();
    let q = ScpiQpd::open(&port, cfg.qpd.baud, cfg.scpi_options())?;
    let d = json!({ "backend": "scpi", "name": q.name(), "port": port, "idn": q.idn() });
    Ok((Box::new(q), d))
}

/// Thorlabs APT devices (and, for a mixed set-up, a GCS stage or a SCPI QPD): KPZ101 cubes as
/// the stage and/or a KPA101 as the QPD.
fn connect_apt(cfg: &Config) -> Result<Instrument, ConnectError> {
    use crate::instrument::thorlabs::kpa101::Kpa101;
    use crate::instrument::thorlabs::kpz101::Kpz101Stage;
    use crate::instrument::{Qpd, Stage};
    let (stage, stage_desc): (Box<dyn Stage>, serde_json::Value) = match cfg.stage.backend {
        KPZ101 => {
            let ps = cfg.stage.ports.clone().unwrap_or_else(|| super::AxisPorts {
                x: String::new(),
                y: String::new(),
                z: String::new(),
            });
            let s = Kpz101Stage::open(
                [&ps.x, &ps.y, &ps.z],
                cfg.kpz_options(),
                cfg.stage.travel_um,
            )?;
            let cubes: Vec<serde_json::Value> = s
                .axes()
                .iter()
                .zip(["x", "y", "z"])
                .map(|(a, ax)| {
                    json!({
                        "axis": ax,
                        "port": a.port(),
                        "device": a.info(),
                        "travel_um": a.travel_um(),
                        "reported_travel_um": a.reported_travel_um(),
                        "enabled_at_connect": a.enabled_at_connect(),
                        "mode_at_connect": a.mode_at_connect(),
                        "gauge_zeroed_at_connect": a.zeroed_at_connect(),
                    })
                })
                .collect();
            let d = json!({
                "backend": "kpz101",
                "name": s.name(),
                "port": { "x": ps.x, "y": ps.y, "z": ps.z },
                "full_scale": cfg.stage.full_scale,
                "tolerance_um": cfg.stage.tolerance_um,
                "cubes": cubes,
            });
            (Box::new(s), d)
        }
        _ => {
            let controllers = cfg.gcs_controllers();
            let s = GcsSplitStage::open_checked(&controllers, cfg.stage.baud)?;
            let d = json!({ "backend": "gcs", "name": s.name() });
            (Box::new(s), d)
        }
    };
    let qport = cfg.qpd.port.clone().unwrap_or_default();
    let (qpd, qpd_desc): (Box<dyn Qpd>, serde_json::Value) = match cfg.qpd.backend {
        KPA101 => {
            let q = Kpa101::open(&qport, cfg.kpa_options())?;
            let d = json!({
                "backend": "kpa101",
                "name": q.name(),
                "port": qport,
                "device": q.info(),
                "sample_rate_hz": q.sample_rate(),
                "calibration": cfg.qpd.calibration,
                "sum_scale": cfg.qpd.sum_scale,
                "x_sign": cfg.qpd.x_sign,
                "signed": cfg.qpd.signed,
            });
            (Box::new(q), d)
        }
        REDPITAYA => open_redpitaya(cfg)?,
        _ => open_scpi(cfg)?,
    };
    Ok(hardware_instrument(cfg, stage, qpd, stage_desc, qpd_desc))
}

/// Connect the Red Pitaya `[qpd]` names, and describe it for the scan metadata.
pub(super) fn open_redpitaya(
    cfg: &Config,
) -> Result<(Box<dyn crate::instrument::Qpd>, serde_json::Value), ConnectError> {
    use crate::instrument::redpitaya::RedPitaya;
    use crate::instrument::Qpd;
    let host = cfg.qpd.host.clone().unwrap_or_default();
    let port = cfg.redpitaya_port()?;
    let q = RedPitaya::open(&host, port, cfg.redpitaya_options())?;
    let d = json!({
        "backend": "redpitaya",
        "name": q.name(),
        "host": host,
        "port": port,
        "address": format!("{host}:{port}"),
        "idn": q.idn(),
        "buffer_samples": q.buffer_size(),
        "channels": cfg.qpd.channels,
        "input_gain": cfg.qpd.input_gain,
        "sample_rate_hz": q.sample_rate(),
        "calibration": cfg.qpd.calibration,
    });
    Ok((Box::new(q), d))
}

/// One controller as found at connect: name, port, `*IDN?`, `SAI?`, the axes it drives and
/// their servo state before anything was switched on.
fn controller_json(s: &GcsStage, port: &str) -> serde_json::Value {
    let xyz = ["x", "y", "z"];
    let mut axes = serde_json::Map::new();
    let mut servo = serde_json::Map::new();
    for (i, (id, on)) in s
        .options()
        .axes
        .iter()
        .zip(s.servo_at_connect())
        .enumerate()
    {
        if let (Some(id), Some(on)) = (id, on) {
            axes.insert(xyz[i].into(), json!(id));
            servo.insert(xyz[i].into(), json!(on));
        }
    }
    json!({
        "name": crate::instrument::Stage::name(s),
        "port": port,
        "idn": s.idn(),
        "sai": s.sai(),
        "axes": axes,
        "servo_at_connect": servo,
        "one_axis_per_query": s.one_axis_per_query(),
    })
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

/// Connect a config with a Nano-Drive and/or an NI board (from `connect::connect_hardware`):
/// the stage (`madlib`, or a PI GCS controller), the QPD (`nidaqmx`, or a Red Pitaya or SCPI
/// digitiser). A failure after the stage was taken drops it, which releases its handle.
fn connect_bench(cfg: &Config) -> Result<crate::instrument::Instrument, ConnectError> {
    use crate::instrument::madlib::MadlibStage;
    use crate::instrument::nidaqmx::NiQpd;
    use serde_json::json;
    let raster = cfg.ni_raster_options()?;
    let mut madlib: Option<MadlibStage> = None;
    let (stage, stage_desc): (Option<Box<dyn Stage>>, serde_json::Value) = match cfg.stage.backend {
        MADLIB => {
            let o = cfg.madlib_options()?;
            let s = MadlibStage::open(o.clone())?;
            let i = s.info();
            let d = json!({
                "backend": "madlib",
                "name": s.name(),
                "library": i.library,
                "serial": i.serial,
                "product_info": {
                    "product_id": i.product_id,
                    "axis_bitmap": i.axis_bitmap,
                    "adc_resolution_bits": i.adc_bits,
                    "dac_resolution_bits": i.dac_bits,
                    "firmware_version": i.firmware_version,
                    "firmware_profile": i.firmware_profile,
                },
                "calibration_um": i.calibration_um,
                "axes": { "x": o.axes[0], "y": o.axes[1], "z": o.axes[2] },
                "tolerance_um": o.tolerance_um,
                "on_target_timeout_ms": cfg.stage.on_target_timeout_ms,
            });
            madlib = Some(s);
            (None, d)
        }
        GCS => {
            let s = crate::instrument::gcs::split::GcsSplitStage::open_checked(
                &cfg.gcs_controllers(),
                cfg.stage.baud,
            )?;
            let d = json!({ "backend": "gcs", "name": s.name() });
            (Some(Box::new(s)), d)
        }
        b => {
            return Err(err(
                "stage.backend",
                format!(
                    "\"{}\" with [qpd] backend = \"nidaqmx\": allowed stages with an NI board are \"madlib\" and \"gcs\"",
                    b.as_str()
                ),
            )
            .into())
        }
    };
    let mut stage = stage;
    let mut stage_desc = stage_desc;
    let (qpd, qpd_desc): (Box<dyn Qpd>, serde_json::Value) = match cfg.qpd.backend {
        NIDAQMX => {
            let o = cfg.ni_qpd_options()?;
            let q = NiQpd::open(o.clone())?;
            let pair = match (&raster, madlib.is_some()) {
                (Some(r), true) => madlib.take().map(|m| (r.clone(), m)),
                _ => None,
            };
            if let Some((r, m)) = pair {
                use crate::instrument::nidaqmx::{raster::NiRaster, stream_stage::NiStreamStage};
                stage_desc["raster"] = json!({
                    "backend": "nidaqmx",
                    "ao": r.ao,
                    "volts_per_um": r.volts_per_um,
                    "position": r.position,
                    "position_volts_per_um": r.position_volts_per_um,
                    "clock": format!("/{}/ao/SampleClock", o.device),
                    "start_trigger": format!("/{}/ao/StartTrigger", o.device),
                });
                let nr = NiRaster::new(q.lib(), r, q.name());
                stage = Some(Box::new(NiStreamStage::new(m, nr)));
            }
            let (product, serial) = q.identity();
            let d = json!({
                "backend": "nidaqmx",
                "name": q.name(),
                "library": q.library(),
                "device": o.device,
                "product_type": product,
                "serial": serial,
                "channels": cfg.qpd.channels,
                "range_v": o.range_v,
                "terminal": o.terminal.name(),
                "sample_rate_hz": o.rate_hz,
                "calibration": cfg.qpd.calibration,
            });
            (Box::new(q), d)
        }
        REDPITAYA => open_redpitaya(cfg)?,
        SCPI => open_scpi(cfg)?,
        b => {
            return Err(err(
                "qpd.backend",
                format!(
                    "\"{}\" with [stage] backend = \"madlib\": allowed digitisers are \"nidaqmx\", \"redpitaya\" and \"scpi\"",
                    b.as_str()
                ),
            )
            .into())
        }
    };
    let stage: Box<dyn Stage> = match (stage, madlib) {
        (Some(s), _) => s,
        (None, Some(m)) => Box::new(m),
        (None, None) => {
            return Err(crate::instrument::DeviceError::Other {
                device: crate::instrument::madlib::FAMILY.backend.into(),
                detail: "no stage was connected".into(),
            }
            .into())
        }
    };
    Ok(hardware_instrument(cfg, stage, qpd, stage_desc, qpd_desc))
}
