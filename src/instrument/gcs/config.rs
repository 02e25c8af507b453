//! The PI GCS stage's part of `bfpscope.toml` (`[stage] backend = "gcs"`): the checks of its
//! ports, its driver settings (one controller, or one per distinct port of a split stage) and
//! its opening with the description scans record.

use super::split::GcsSplitStage;
use super::{GcsOptions, GcsStage, GCS};
use crate::instrument::family::{
    ConnectHelp, Family, Open, OpenError, Opened, Section, StageDefaults,
};
use crate::instrument::link::TCP_PREFIX;
use crate::instrument::tables::{bad, SectionError, StageConfig, Tables, AXIS_NAMES};
use crate::instrument::Stage;
use serde_json::json;
use std::time::Duration;

/// The family, as `instrument::registry` lists it: its names, `connect` keys, defaults,
/// section and help.
pub const FAMILY: Family = Family {
    stages: &[GCS.0],
    keys: &["stage_port", "baud", "stage_baud", "timeout_ms"],
    stage_defaults: StageDefaults {
        // `#5` is one byte each way (0.26 ms of wire per poll at 115200 baud): polling every
        // millisecond costs the controller little
        poll_ms: 1,
        settle_s: None,
    },
    section: Section::stage(validate, open_stage),
    help: ConnectHelp {
        backend: "\"hardware\" (alias \"gcs\", \"scpi\": PI GCS stage + SCPI QPD on serial ports)",
        about: "\"hardware\": the PI GCS 2.0 stage and SCPI QPD drivers on the config's ports (stage_port, qpd_port, baud, … \
             override them); connecting identifies both devices, switches the servos on and reads the travel range.",
    },
    ..Family::new("gcs", "hardware", Open::config("gcs", "scpi"))
};

/// `stage.port` and `stage.ports` of a GCS stage: one of the two, each port `tcp://HOST:PORT`
/// or a serial path.
fn validate(t: &Tables) -> Result<(), SectionError> {
    let s = t.stage;
    if s.backend != GCS {
        return Ok(());
    }
    match (&s.port, &s.ports) {
        (Some(p), Some(ps)) => {
            return Err(bad(
                "stage.ports",
                format!(
                    "both stage.port = {p:?} and stage.ports = {{ x = {:?}, y = {:?}, z = {:?} }} are set: \
                     give stage.port (one controller for x, y and z) or stage.ports (the controller of \
                     each axis), not both",
                    ps.x, ps.y, ps.z
                ),
            ))
        }
        (None, None) => {
            return Err(bad(
                "stage.port",
                "required when backend = \"gcs\" (e.g. \"/dev/ttyUSB0\" or \"tcp://192.168.0.10:50000\"; \
                 or stage.ports = { x = …, y = …, z = … } for a stage split across controllers)",
            ))
        }
        _ => {}
    }
    let keyed: Vec<(String, &str)> = match (&s.port, &s.ports) {
        (Some(p), _) => vec![("stage.port".into(), p.as_str())],
        (_, Some(ps)) => (0..3)
            .map(|i| (format!("stage.ports.{}", AXIS_NAMES[i]), ps.get(i)))
            .collect(),
        _ => vec![],
    };
    for (key, p) in keyed {
        if p.trim().is_empty() {
            return Err(bad(
                &key,
                "empty: a serial port (e.g. \"/dev/ttyUSB0\") or \"tcp://HOST:PORT\" (e.g. \
                 \"tcp://192.168.0.10:50000\")",
            ));
        }
        if let Some(addr) = p.strip_prefix(TCP_PREFIX) {
            let ok = addr.rsplit_once(':').is_some_and(|(host, port)| {
                !host.is_empty() && port.parse::<u16>().is_ok_and(|n| n > 0)
            });
            if !ok {
                return Err(bad(
                    &key,
                    format!(
                        "{p:?} is not tcp://HOST:PORT: allowed are a serial port (e.g. \"/dev/ttyUSB0\") or \
                         tcp:// with a host and a port 1–65535 (PI controllers: \"tcp://192.168.0.10:50000\")"
                    ),
                ));
            }
        }
    }
    Ok(())
}

/// Driver settings for the GCS stage on one controller (all three axes).
pub fn options(s: &StageConfig) -> GcsOptions {
    GcsOptions {
        axes: [0, 1, 2].map(|i| Some(s.axes.get(i).to_string())),
        timeout: Duration::from_millis(s.timeout_ms),
        on_target_timeout: Duration::from_millis(s.on_target_timeout_ms),
        poll_interval: Duration::from_millis(s.poll_ms.unwrap_or(FAMILY.stage_defaults.poll_ms)),
        servo_on_connect: s.servo_on_connect,
        units_per_um: s.units_per_um,
        one_axis_per_query: s.one_axis_per_query,
        motion_status: s.motion_status,
        confirm_on_target: true,
        trigger_line: s.trigger_line,
        servo_cycle_s: s.servo_cycle_s,
        max_wave_points: s.max_wave_points,
        max_record_points: s.max_record_points,
    }
}

/// The GCS controllers of the stage: (port, driver settings naming the axes on that port),
/// one per distinct port in x, y, z order; a single entry for `stage.port`.
pub fn controllers(s: &StageConfig) -> Vec<(String, GcsOptions)> {
    let base = options(s);
    match &s.ports {
        None => vec![(s.port.clone().unwrap_or_default(), base)],
        Some(ps) => s
            .distinct_ports()
            .into_iter()
            .map(|port| {
                let mut o = base.clone();
                for i in 0..3 {
                    if ps.get(i) != port {
                        o.axes[i] = None;
                    }
                }
                (port, o)
            })
            .collect(),
    }
}

/// Open the GCS stage read-only (nothing is switched on before `connect` has checked the
/// limits): one controller, or a stage split across several.
fn open_stage(t: &Tables) -> Result<Opened<Box<dyn Stage>>, OpenError> {
    let s = t.stage;
    let ctl = controllers(s);
    let (stage, parts): (Box<dyn Stage>, Vec<serde_json::Value>) = if ctl.len() == 1 {
        let (port, o) = &ctl[0];
        let g = GcsStage::open_checked(port, s.baud, o.clone())?;
        let d = controller_json(&g, port);
        (Box::new(g), vec![d])
    } else {
        let g = GcsSplitStage::open_checked(&ctl, s.baud)?;
        let d = g
            .controllers()
            .iter()
            .zip(&ctl)
            .map(|(c, (port, _))| controller_json(c, port))
            .collect();
        (Box::new(g), d)
    };
    let port = match &s.ports {
        Some(p) => json!({ "x": p.x, "y": p.y, "z": p.z }),
        None => json!(s.port.clone().unwrap_or_default()),
    };
    let idn: Vec<&str> = parts
        .iter()
        .map(|p| p["idn"].as_str().unwrap_or_default())
        .collect();
    let description = json!({
        "backend": GCS,
        "name": stage.name(),
        "port": port,
        "baud": s.baud,
        "idn": idn.join(" + "),
        "axes": { "x": s.axes.x, "y": s.axes.y, "z": s.axes.z },
        "units_per_um": s.units_per_um,
        "controllers": parts,
    });
    Ok(Opened {
        device: stage,
        description,
    })
}

/// One controller as found at connect: name, port, `*IDN?`, `SAI?`, the axes it drives and
/// their servo state before anything was switched on.
fn controller_json(s: &GcsStage, port: &str) -> serde_json::Value {
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
            axes.insert(AXIS_NAMES[i].into(), json!(id));
            servo.insert(AXIS_NAMES[i].into(), json!(on));
        }
    }
    json!({
        "name": Stage::name(s),
        "port": port,
        "idn": s.idn(),
        "sai": s.sai(),
        "axes": axes,
        "servo_at_connect": servo,
        "one_axis_per_query": s.one_axis_per_query(),
    })
}
