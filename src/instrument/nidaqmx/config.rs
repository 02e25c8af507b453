//! The NI board's part of `bfpscope.toml`: the QPD digitiser (`[qpd] backend = "nidaqmx"`)
//! and its hardware-timed raster (`[raster] backend = "nidaqmx"`, AO driving a Nano-Drive's
//! external inputs): their checks, driver settings, and the opening of the QPD alone or of
//! the Nano-Drive and the board together, with the descriptions scans record.

use super::raster::{ExternalInput, NiRaster, NiRasterOptions};
use super::stream_stage::NiStreamStage;
use super::{
    parse_channel, NiInputs, NiQpd, NiQpdOptions, Terminal, NIDAQMX, PCI6120_MAX_RANGE_V,
    PCI6120_MAX_RATE_HZ,
};
use crate::instrument::family::{Family, Open, OpenError, Opened, OpenedPair, Section};
use crate::instrument::madlib::MADLIB;
use crate::instrument::tables::{
    bad, only_for, QpdChannels, QpdConfig, RasterConfig, SectionError, Tables,
};
use crate::instrument::Qpd;
use serde_json::json;
use std::time::Duration;

/// The family, as `instrument::registry` lists it: its names, `connect` keys, defaults,
/// section and help.
pub const FAMILY: Family = Family {
    qpds: &[NIDAQMX.0],
    keys: &["timeout_ms"],
    section: Section {
        open_pair: Some(open_pair),
        ..Section::qpd(validate, open_qpd)
    },
    ..Family::new("nidaqmx", "bench", Open::config("madlib", "nidaqmx"))
};

/// The board's keys are valid (and refused for another QPD); `[raster]` names the board, with
/// the board as the QPD and a Nano-Drive as the stage.
fn validate(t: &Tables) -> Result<(), SectionError> {
    let q = t.qpd;
    if q.backend == NIDAQMX {
        qpd_options(q)?;
    } else {
        only_for(
            NIDAQMX.as_str(),
            &format!("the QPD is \"{}\"", q.backend.as_str()),
            [
                ("qpd.library", q.library.is_some()),
                ("qpd.device", q.device.is_some()),
                // the SCPI digitiser's range comes from the config too
                (
                    "qpd.range_v",
                    q.range_v.is_some() && q.backend != crate::instrument::scpi::SCPI,
                ),
                ("qpd.terminal", q.terminal.is_some()),
                ("qpd.rate_hz", q.rate_hz.is_some()),
            ],
        )?;
        if let QpdChannels::Names(_) = q.channels {
            return Err(bad(
                "qpd.channels",
                format!(
                    "input names (\"ai0\"…) are for backend = \"nidaqmx\"; the QPD is \"{}\" (a Red Pitaya's inputs are numbers 1–4)",
                    q.backend.as_str()
                ),
            ));
        }
    }
    let Some(r) = t.raster else {
        return Ok(());
    };
    if r.backend != NIDAQMX {
        return Err(bad(
            "raster.backend",
            format!(
                "\"{}\": allowed is \"nidaqmx\" (the NI board's hardware-timed raster)",
                r.backend.as_str()
            ),
        ));
    }
    if q.backend != NIDAQMX {
        return Err(bad("raster.backend", format!("\"nidaqmx\" needs [qpd] backend = \"nidaqmx\" (the raster records the QPD on the NI board); the QPD is \"{}\"", q.backend.as_str())));
    }
    if t.stage.backend != MADLIB {
        return Err(bad("raster.backend", format!("\"nidaqmx\" drives a Nano-Drive's external inputs: needs [stage] backend = \"madlib\" (the stage is \"{}\")", t.stage.backend.as_str())));
    }
    raster_options(q, r).map(|_| ())
}

/// NI QPD driver settings from `[qpd]`.
pub fn qpd_options(q: &QpdConfig) -> Result<NiQpdOptions, SectionError> {
    let device = q.device.clone().unwrap_or_default();
    if device.trim().is_empty() || device.contains('/') || device.contains(char::is_whitespace) {
        return Err(bad(
            "qpd.device",
            if q.device.is_none() {
                "required when backend = \"nidaqmx\": the board's name in NI MAX (e.g. \"Dev1\")"
                    .to_string()
            } else {
                format!(
                    "{device:?} is not a device name: the board's name in NI MAX (e.g. \"Dev1\")"
                )
            },
        ));
    }
    let inputs = inputs(q, &device)?;
    let range_v = q.range_v.unwrap_or(10.0);
    if !(range_v.is_finite() && range_v > 0.0 && range_v <= PCI6120_MAX_RANGE_V) {
        return Err(bad("qpd.range_v", format!("{range_v}: the input range ±V, above 0 and at most 42 (PCI-6120: 0.2, 0.5, 1, 2, 5, 10, 20, 42)")));
    }
    let terminal = Terminal::parse(q.terminal.as_deref().unwrap_or("diff"))
        .map_err(|m| bad("qpd.terminal", m))?;
    let rate_hz = q.rate_hz.unwrap_or(PCI6120_MAX_RATE_HZ);
    if !(rate_hz.is_finite() && rate_hz > 0.0 && rate_hz <= 10e6) {
        return Err(bad(
            "qpd.rate_hz",
            format!(
                "{rate_hz} Hz: the sample rate per channel, above 0 (PCI-6120: at most 800000)"
            ),
        ));
    }
    Ok(NiQpdOptions {
        library: q.library.clone(),
        device,
        inputs,
        range_v,
        terminal,
        rate_hz,
        timeout_margin: Duration::from_millis(q.timeout_ms),
        calibration: q.calibration,
        sum_floor_v: q.sum_floor,
    })
}

/// `qpd.channels` as the board's inputs: the amplifier's outputs (sx, sy, sum) or the four
/// quadrants, each its own input.
fn inputs(q: &QpdConfig, device: &str) -> Result<NiInputs, SectionError> {
    let names = match &q.channels {
        QpdChannels::Names(m) => m.clone(),
        QpdChannels::Inputs(_) => {
            return Err(bad(
                "qpd.channels",
                "required as input names when backend = \"nidaqmx\": { sx = \"ai0\", sy = \"ai1\", sum = \"ai2\" } or { q1 = \"ai0\", q2 = \"ai1\", q3 = \"ai2\", q4 = \"ai3\" }",
            ))
        }
    };
    let ch = |k: &str| -> Result<String, SectionError> {
        parse_channel("ai", &names[k], device).map_err(|m| bad(&format!("qpd.channels.{k}"), m))
    };
    let keys: Vec<&str> = names.keys().map(String::as_str).collect();
    let inputs = if keys == ["sum", "sx", "sy"] {
        NiInputs::Signals {
            sx: ch("sx")?,
            sy: ch("sy")?,
            sum: ch("sum")?,
        }
    } else if keys == ["q1", "q2", "q3", "q4"] {
        NiInputs::Quadrants([ch("q1")?, ch("q2")?, ch("q3")?, ch("q4")?])
    } else {
        return Err(bad(
            "qpd.channels",
            format!(
                "keys {}: allowed are sx, sy, sum (the QPD amplifier's outputs) or q1, q2, q3, q4 (the quadrants)",
                keys.join(", ")
            ),
        ));
    };
    let list = inputs.names();
    for i in 0..list.len() {
        if list[i + 1..].contains(&list[i]) {
            return Err(bad(
                "qpd.channels",
                format!(
                    "{:?} is given twice: each signal needs its own input",
                    list[i]
                ),
            ));
        }
    }
    Ok(inputs)
}

/// A scale in volts per µm, above 0.
fn positive_or_err(key: &str, v: Option<f64>, what: &str) -> Result<f64, SectionError> {
    match v {
        Some(v) if v.is_finite() && v > 0.0 => Ok(v),
        Some(v) => Err(bad(key, format!("{v}: {what} must be a positive number of volts per µm (e.g. 0.1333: 10 V over 75 µm)"))),
        None => Err(bad(key, format!("required: {what} in volts per µm (e.g. 0.1333: 10 V over 75 µm)"))),
    }
}

/// The NI channel `v` of `kind` (`"ao"`, `"ai"`) on `dev` that the key `key` names, parsed;
/// `None` when the key is left out.
fn channel_at(
    key: &str,
    kind: &str,
    v: Option<&str>,
    dev: &str,
) -> Result<Option<String>, SectionError> {
    v.map(|a| parse_channel(kind, a, dev).map_err(|m| bad(key, m)))
        .transpose()
}

/// The NI raster's settings from `[raster]` and the board's `[qpd]`.
pub fn raster_options(q: &QpdConfig, r: &RasterConfig) -> Result<NiRasterOptions, SectionError> {
    let qo = qpd_options(q)?;
    let dev = qo.device.clone();
    // as `channel_at`, for a key that is required: `what` says what is wired there
    let required =
        |key: &str, kind: &str, v: Option<&str>, what: &str| -> Result<String, SectionError> {
            channel_at(key, kind, v, &dev)?.ok_or_else(|| bad(key, format!("required: {what}")))
        };
    let ao_x = required(
        "raster.ao.x",
        "ao",
        r.ao.x.as_deref(),
        "the NI output driving the fast axis's external input (e.g. \"ao0\")",
    )?;
    let ao_y = channel_at("raster.ao.y", "ao", r.ao.y.as_deref(), &dev)?;
    if ao_y.as_deref() == Some(ao_x.as_str()) {
        return Err(bad(
            "raster.ao.y",
            format!("{ao_x:?} is raster.ao.x too: each axis needs its own output"),
        ));
    }
    let vx = positive_or_err(
        "raster.volts_per_um.x",
        r.volts_per_um.x,
        "the x external input's scale",
    )?;
    let vy = match ao_y {
        Some(_) => Some(positive_or_err(
            "raster.volts_per_um.y",
            r.volts_per_um.y,
            "the y external input's scale",
        )?),
        None => None,
    };
    if r.position.y.is_some() || r.position_volts_per_um.y.is_some() {
        return Err(bad(
            "raster.position.y",
            "only the fast axis's sensor monitor (position.x) is recorded",
        ));
    }
    let px = required(
        "raster.position.x",
        "ai",
        r.position.x.as_deref(),
        "the NI input wired to the fast axis's sensor-monitor output (e.g. \"ai3\")",
    )?;
    if qo.inputs.names().contains(&px) {
        return Err(bad("raster.position.x", format!("{px:?} is already a QPD input (qpd.channels): the sensor monitor needs its own input")));
    }
    let pvx = positive_or_err(
        "raster.position_volts_per_um.x",
        r.position_volts_per_um.x,
        "the sensor monitor's scale",
    )?;
    let external_input = match r.external_input.as_deref() {
        None => ExternalInput::Sum,
        Some(v) => ExternalInput::parse(v).ok_or_else(|| {
            bad(
                "raster.external_input",
                format!(
                    "\"{v}\": allowed are \"sum\" (the Nano-Drive adds its external input to the USB command, as MCL documents it; the default) and \"replace\" (it follows the external input alone)"
                ),
            )
        })?,
    };
    Ok(NiRasterOptions {
        qpd: qo,
        external_input,
        ao: [ao_x, ao_y.unwrap_or_default()],
        volts_per_um: [vx, vy.unwrap_or(0.0)],
        position: px,
        position_volts_per_um: pvx,
    })
}

/// The board and its description.
fn open_board(q: &QpdConfig) -> Result<(NiQpd, NiQpdOptions, serde_json::Value), OpenError> {
    let o = qpd_options(q)?;
    let qpd = NiQpd::open(o.clone())?;
    let (product, serial) = qpd.identity();
    let description = json!({
        "backend": NIDAQMX,
        "name": qpd.name(),
        "library": qpd.library(),
        "device": o.device,
        "product_type": product,
        "serial": serial,
        "channels": q.channels,
        "range_v": o.range_v,
        "terminal": o.terminal.name(),
        "sample_rate_hz": o.rate_hz,
        "calibration": q.calibration,
    });
    Ok((qpd, o, description))
}

fn open_qpd(t: &Tables) -> Result<Opened<Box<dyn Qpd>>, OpenError> {
    let (qpd, _, description) = open_board(t.qpd)?;
    Ok(Opened {
        device: Box::new(qpd),
        description,
    })
}

/// With `[raster]`: the Nano-Drive, then the board, the stage's fast lines streamed by the
/// board (a failure after the stage was taken drops it, which releases its handle).
fn open_pair(t: &Tables) -> Result<Option<OpenedPair>, OpenError> {
    let Some(r) = t.raster else {
        return Ok(None);
    };
    let ro = raster_options(t.qpd, r)?;
    let mut stage = crate::instrument::madlib::config::open(t.stage)?;
    let (qpd, o, description) = open_board(t.qpd)?;
    stage.description["raster"] = json!({
        "backend": NIDAQMX,
        "ao": ro.ao,
        "volts_per_um": ro.volts_per_um,
        "position": ro.position,
        "position_volts_per_um": ro.position_volts_per_um,
        "clock": format!("/{}/ao/SampleClock", o.device),
        "start_trigger": format!("/{}/ao/StartTrigger", o.device),
    });
    let raster = NiRaster::new(qpd.lib(), ro, qpd.name());
    Ok(Some((
        Opened {
            device: Box::new(NiStreamStage::new(stage.device, raster)),
            description: stage.description,
        },
        Opened {
            device: Box::new(qpd),
            description,
        },
    )))
}
