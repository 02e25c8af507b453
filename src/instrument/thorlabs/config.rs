//! The Thorlabs K-Cubes' part of `bfpscope.toml`: three KPZ101 piezo cubes as the stage
//! (`[stage] backend = "kpz101"`, one cube per axis in `stage.ports`) and a KPA101 position
//! aligner as the QPD (`[qpd] backend = "kpa101"`): their checks, driver settings and opening
//! with the descriptions scans record.

use super::kpa101::{Kpa101, KpaOptions};
use super::kpz101::{Kpz101Stage, KpzOptions};
use super::{KPA101, KPZ101};
use crate::instrument::family::{
    ConnectHelp, Family, Open, OpenError, Opened, Section, StageDefaults,
};
use crate::instrument::link::TCP_PREFIX;
use crate::instrument::tables::{
    bad, AxisPorts, QpdConfig, SectionError, StageConfig, Tables, AXIS_NAMES,
};
use crate::instrument::{Qpd, Stage};
use serde_json::json;
use std::time::Duration;

/// The family, as `instrument::registry` lists it: its names, `connect` keys, defaults,
/// section and help.
pub const FAMILY: Family = Family {
    aliases: &["kpz101", "kpa101"],
    stages: &[KPZ101.0],
    qpds: &[KPA101.0],
    keys: &["qpd_port", "stage_ports", "timeout_ms"],
    stage_defaults: StageDefaults {
        // each poll is an `MGMSG_PZ_REQ_OUTPUTPOS` request and reply, and a strain-gauge
        // reading taken every millisecond catches the actuator still on its way, inside the
        // tolerance before it has settled
        poll_ms: 10,
        settle_s: None,
    },
    section: Section {
        open_qpd: Some(open_qpd),
        ..Section::stage(validate, open_stage)
    },
    help: ConnectHelp::entry("\"thorlabs\" (alias \"kpz101\", \"kpa101\": three KPZ101 cubes + a KPA101 position aligner)"),
    ..Family::new("thorlabs", "thorlabs", Open::config("kpz101", "kpa101"))
};

fn validate(t: &Tables) -> Result<(), SectionError> {
    if t.stage.backend == KPZ101 {
        validate_kpz101(t.stage)?;
    }
    if t.qpd.backend == KPA101 {
        validate_kpa101(t.qpd)?;
    }
    Ok(())
}

/// `kpz101`: one cube per axis, so `stage.ports` with three different serial ports.
fn validate_kpz101(s: &StageConfig) -> Result<(), SectionError> {
    let Some(ps) = &s.ports else {
        return Err(bad(
            "stage.ports",
            match &s.port {
                Some(p) => format!(
                    "required when backend = \"kpz101\" (one cube per axis); stage.port = {p:?} names one: \
                     write stage.ports = {{ x = \"/dev/ttyUSB0\", y = \"/dev/ttyUSB1\", z = \"/dev/ttyUSB2\" }}"
                ),
                None => "required when backend = \"kpz101\" (one cube per axis): e.g. stage.ports = \
                         { x = \"/dev/ttyUSB0\", y = \"/dev/ttyUSB1\", z = \"/dev/ttyUSB2\" }"
                    .to_string(),
            },
        ));
    };
    if let Some(p) = &s.port {
        return Err(bad(
            "stage.port",
            format!("{p:?}: with backend = \"kpz101\" give stage.ports only (one cube per axis)"),
        ));
    }
    for i in 0..3 {
        let p = ps.get(i);
        let key = format!("stage.ports.{}", AXIS_NAMES[i]);
        if p.trim().is_empty() || p.starts_with(TCP_PREFIX) {
            return Err(bad(
                &key,
                format!("{p:?}: a KPZ101 is a USB-serial device: allowed is a serial port (e.g. \"/dev/ttyUSB0\")"),
            ));
        }
        for j in 0..i {
            if ps.get(j) == p {
                return Err(bad(
                    &key,
                    format!(
                        "{p:?} is also stage.ports.{}: a KPZ101 drives one axis, each axis needs its own cube",
                        AXIS_NAMES[j]
                    ),
                ));
            }
        }
    }
    if !(s.full_scale == 32767 || s.full_scale == 65535) {
        return Err(bad(
            "stage.full_scale",
            format!(
                "{}: allowed values are 32767 (Thorlabs' document) and 65535",
                s.full_scale
            ),
        ));
    }
    if !(s.tolerance_um.is_finite() && s.tolerance_um > 0.0) {
        return Err(bad(
            "stage.tolerance_um",
            format!("{}: must be a positive distance in µm", s.tolerance_um),
        ));
    }
    if let Some(t) = s.travel_um {
        for i in 0..3 {
            if !(t[i].is_finite() && t[i] > 0.0 && t[i] <= 6553.5) {
                return Err(bad(
                    "stage.travel_um",
                    format!(
                        "{}: {} µm must be a positive travel up to 6553.5 µm",
                        AXIS_NAMES[i], t[i]
                    ),
                ));
            }
        }
    }
    Ok(())
}

/// `kpa101`: its serial port, the X sign and the Sum scale.
fn validate_kpa101(q: &QpdConfig) -> Result<(), SectionError> {
    q.require_port()?;
    if !(q.x_sign == 1.0 || q.x_sign == -1.0) {
        return Err(bad(
            "qpd.x_sign",
            format!("{}: allowed values are 1 and -1", q.x_sign),
        ));
    }
    if !(q.sum_scale.is_finite() && q.sum_scale > 0.0) {
        return Err(bad(
            "qpd.sum_scale",
            format!(
                "{}: must be a positive number of volts per count (document: 10/65535 = {:e}; \
                 pylablib: 20/32767 = {:e})",
                q.sum_scale,
                10.0 / 65535.0,
                20.0 / 32767.0
            ),
        ));
    }
    Ok(())
}

/// Driver settings for the KPZ101 cubes.
pub fn kpz_options(s: &StageConfig) -> KpzOptions {
    KpzOptions {
        timeout: Duration::from_millis(s.timeout_ms),
        on_target_timeout: Duration::from_millis(s.on_target_timeout_ms),
        poll_interval: Duration::from_millis(s.poll_ms.unwrap_or(FAMILY.stage_defaults.poll_ms)),
        tolerance_um: s.tolerance_um,
        travel_um: None,
        full_scale: s.full_scale as u16,
        rtscts: true,
        zero_at_connect: s.zero_at_connect,
        zero_timeout: Duration::from_millis(s.zero_timeout_ms),
    }
}

/// Driver settings for the KPA101.
pub fn kpa_options(q: &QpdConfig) -> KpaOptions {
    KpaOptions {
        timeout: Duration::from_millis(q.timeout_ms),
        calibration: q.calibration,
        sum_scale: q.sum_scale,
        x_sign: q.x_sign,
        signed: q.signed,
        rtscts: true,
        sum_floor_v: q.sum_floor,
    }
}

/// Open the three KPZ101 cubes, one per axis.
fn open_stage(t: &Tables) -> Result<Opened<Box<dyn Stage>>, OpenError> {
    let s = t.stage;
    let ps = s.ports.clone().unwrap_or_else(|| AxisPorts {
        x: String::new(),
        y: String::new(),
        z: String::new(),
    });
    let stage = Kpz101Stage::open([&ps.x, &ps.y, &ps.z], kpz_options(s), s.travel_um)?;
    let cubes: Vec<serde_json::Value> = stage
        .axes()
        .iter()
        .zip(AXIS_NAMES)
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
    let description = json!({
        "backend": KPZ101,
        "name": stage.name(),
        "port": { "x": ps.x, "y": ps.y, "z": ps.z },
        "full_scale": s.full_scale,
        "tolerance_um": s.tolerance_um,
        "cubes": cubes,
    });
    Ok(Opened {
        device: Box::new(stage),
        description,
    })
}

/// Open the KPA101 position aligner on `[qpd] port`.
fn open_qpd(t: &Tables) -> Result<Opened<Box<dyn Qpd>>, OpenError> {
    let q = t.qpd;
    let port = q.port.clone().unwrap_or_default();
    let qpd = Kpa101::open(&port, kpa_options(q))?;
    let description = json!({
        "backend": KPA101,
        "name": qpd.name(),
        "port": port,
        "device": qpd.info(),
        "sample_rate_hz": qpd.sample_rate(),
        "calibration": q.calibration,
        "sum_scale": q.sum_scale,
        "x_sign": q.x_sign,
        "signed": q.signed,
    });
    Ok(Opened {
        device: Box::new(qpd),
        description,
    })
}
