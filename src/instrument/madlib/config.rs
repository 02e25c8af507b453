//! The Nano-Drive's part of `bfpscope.toml` (`[stage] backend = "madlib"`): the library,
//! serial number, Madlib axis numbers and tolerance checked, the driver settings, and the
//! stage's opening with the description scans record.

use super::{MadlibOptions, MadlibStage, MADLIB};
use crate::instrument::family::{
    ConnectHelp, Family, Open, OpenError, Opened, Section, StageDefaults,
};
use crate::instrument::tables::{bad, only_for, SectionError, StageConfig, Tables, AXIS_NAMES};
use crate::instrument::Stage;
use serde_json::json;
use std::time::Duration;

/// The family, as `instrument::registry` lists it: its names, `connect` keys, defaults,
/// section and help.
pub const FAMILY: Family = Family {
    stages: &[MADLIB.0],
    keys: &["timeout_ms"],
    stage_defaults: StageDefaults {
        // the readings back to back: each `MCL_SingleReadN` is a USB round trip of its own
        // (≈ 0.2 ms), so the link sets the pace and a move ends as soon as the readings are on
        // target (a 5 ms poll cost a 31 nm step 7 ms)
        poll_ms: 0,
        // settled on its readings (`tolerance_um`, two in a row): no fixed settle after them
        settle_s: Some(0.0),
    },
    section: Section::stage(validate, open_stage),
    help: ConnectHelp::entry("\"madlib\" (alias \"nidaqmx\", \"bench\": the paper's bench, a Mad City Labs Nano-Drive + an NI DAQ board through their vendor libraries, the rest from the config's [stage], [qpd] and [raster])"),
    ..Family::new("madlib", "bench", Open::config("madlib", "nidaqmx"))
};

/// A Nano-Drive's keys are valid; its keys (library, serial) are refused for another stage.
fn validate(t: &Tables) -> Result<(), SectionError> {
    let s = t.stage;
    if s.backend != MADLIB {
        return only_for(
            MADLIB.as_str(),
            &format!("the stage is \"{}\"", s.backend.as_str()),
            [
                ("stage.library", s.library.is_some()),
                ("stage.serial", s.serial.is_some()),
            ],
        );
    }
    options(s).map(|_| ())
}

/// Nano-Drive driver settings from `[stage]`.
pub fn options(s: &StageConfig) -> Result<MadlibOptions, SectionError> {
    let mut axes = [0u32; 3];
    for (i, a) in axes.iter_mut().enumerate() {
        let v = s.axes.get(i);
        *a = match v.trim().parse::<u32>() {
            Ok(n) if (1..=4).contains(&n) => n,
            _ => {
                return Err(bad(
                    &format!("stage.axes.{}", AXIS_NAMES[i]),
                    format!(
                    "{v:?} is not a Nano-Drive axis: allowed are 1–4 (1 = X, 2 = Y, 3 = Z, 4 = A)"
                ),
                ))
            }
        };
    }
    if let Some(n) = s.serial {
        if n <= 0 {
            return Err(bad("stage.serial", format!("{n}: a Nano-Drive serial number is a positive number (the label on the controller, or MCL_GetSerialNumber)")));
        }
    }
    if let Some(p) = &s.library {
        if p.as_os_str().is_empty() {
            return Err(bad("stage.library", "empty: the path of libmadlib.so (or Madlib.dll), or leave the key out to search the usual places"));
        }
    }
    if !(s.tolerance_um.is_finite() && s.tolerance_um > 0.0 && s.tolerance_um <= 10.0) {
        return Err(bad(
            "stage.tolerance_um",
            format!("{}: must be above 0 and at most 10 µm", s.tolerance_um),
        ));
    }
    Ok(MadlibOptions {
        library: s.library.clone(),
        serial: s.serial,
        axes,
        tolerance_um: s.tolerance_um,
        on_target_timeout: Duration::from_millis(s.on_target_timeout_ms),
        poll_interval: Duration::from_millis(s.poll_ms.unwrap_or(FAMILY.stage_defaults.poll_ms)),
    })
}

/// Open the Nano-Drive `[stage]` names, with its description (the NI raster wraps it).
pub fn open(s: &StageConfig) -> Result<Opened<MadlibStage>, OpenError> {
    let o = options(s)?;
    let stage = MadlibStage::open(o.clone())?;
    let i = stage.info();
    let description = json!({
        "backend": MADLIB,
        "name": stage.name(),
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
        "on_target_timeout_ms": s.on_target_timeout_ms,
    });
    Ok(Opened {
        device: stage,
        description,
    })
}

fn open_stage(t: &Tables) -> Result<Opened<Box<dyn Stage>>, OpenError> {
    let o = open(t.stage)?;
    Ok(Opened {
        device: Box::new(o.device),
        description: o.description,
    })
}
