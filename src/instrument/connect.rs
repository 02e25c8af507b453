//! Build an [`Instrument`] from the config: simulated, or a GCS stage and a SCPI QPD on
//! serial ports. Also computes the limits in force (soft limits ∩ the travel range the stage
//! reports), which `acquire/` enforces.

use super::config::{effective_limits, Backend, Config, ConfigError, SafetyLimits};
use super::gcs::GcsStage;
use super::scpi::ScpiQpd;
use super::{DeviceError, Instrument, WallClock};
use serde_json::json;
use std::sync::Arc;

/// A connected instrument and the limits in force for it.
pub struct Connected {
    pub instrument: Instrument,
    /// Soft limits ∩ travel range, max step and speed (µm, µm/s).
    pub limits: SafetyLimits,
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
/// - `gcs` + `scpi`: open both ports, identify both devices (`*IDN?`), switch the servos on,
///   read the travel range (`TMN?`/`TMX?`) and the sample rate. The clock is the wall clock.
///
/// In both cases the stage's travel range is intersected with the `[limits]` soft limits. A
/// failure names the device and what it said; a half-opened pair is closed again.
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
        (Backend::Sim, Backend::Sim) => make_sim(cfg).map_err(ConnectError::Sim)?,
        _ => connect_hardware(cfg)?,
    };
    let travel = instrument.stage.travel_range()?;
    let axes = effective_limits(&cfg.limits, travel)?;
    let limits = SafetyLimits {
        axes,
        max_step_um: cfg.limits.max_step_um,
        max_speed_um_s: cfg.stage.max_speed_um_s,
    };
    if let serde_json::Value::Object(m) = &mut instrument.description {
        m.insert("travel_um".into(), json!(travel));
        m.insert(
            "limits".into(),
            serde_json::to_value(&limits).unwrap_or_default(),
        );
    }
    Ok(Connected { instrument, limits })
}

fn connect_hardware(cfg: &Config) -> Result<Instrument, ConnectError> {
    let sport = cfg.stage.port.clone().unwrap_or_default();
    let qport = cfg.qpd.port.clone().unwrap_or_default();
    let stage = GcsStage::open(&sport, cfg.stage.baud, cfg.gcs_options())?;
    // If the QPD fails, `stage` is dropped here and its port closed.
    let qpd = ScpiQpd::open(&qport, cfg.qpd.baud, cfg.scpi_options())?;
    let description = json!({
        "stage": {
            "backend": "gcs",
            "name": super::Stage::name(&stage),
            "port": sport,
            "baud": cfg.stage.baud,
            "idn": stage.idn(),
            "axes": { "x": cfg.stage.axes.x, "y": cfg.stage.axes.y, "z": cfg.stage.axes.z },
            "units_per_um": cfg.stage.units_per_um,
        },
        "qpd": {
            "backend": "scpi",
            "name": super::Qpd::name(&qpd),
            "port": qport,
            "baud": cfg.qpd.baud,
            "idn": qpd.idn(),
            "sample_rate_hz": super::Qpd::sample_rate(&qpd),
            "calibration": cfg.qpd.calibration,
        },
        "settle_s": cfg.stage.settle_s,
    });
    Ok(Instrument {
        stage: Box::new(stage),
        qpd: Box::new(qpd),
        clock: Arc::new(WallClock::default()),
        settle_s: cfg.stage.settle_s,
        description,
    })
}
