//! The Red Pitaya's part of `bfpscope.toml` (`[qpd] backend = "redpitaya"`): the board's host,
//! TCP port, input map and rate checked, its driver settings, and its opening with the
//! description scans record.

use super::{RedPitaya, RedPitayaOptions, BASE_RATE_HZ, DEFAULT_PORT, REDPITAYA};
use crate::instrument::family::{ConnectHelp, Family, Open, OpenError, Opened, Section};
use crate::instrument::tables::{bad, QpdChannels, QpdConfig, SectionError, Tables};
use crate::instrument::Qpd;
use serde_json::json;
use std::time::Duration;

/// The family, as `instrument::registry` lists it: its names, `connect` keys, defaults,
/// section and help.
pub const FAMILY: Family = Family {
    qpds: &[REDPITAYA.0],
    keys: &["qpd_host", "qpd_port", "timeout_ms"],
    section: Section::qpd(validate, open_qpd),
    help: ConnectHelp::entry("\"redpitaya\" (PI GCS stage + a Red Pitaya STEMlab QPD over TCP)"),
    ..Family::new("redpitaya", "hardware", Open::config("gcs", "redpitaya"))
};

/// `[qpd]` for a Red Pitaya: `host` required (a name or address, without a port), `port`
/// a TCP port number, the channel map inputs 1–4 and different, a positive sample rate up
/// to the board's 125 MHz.
fn validate(t: &Tables) -> Result<(), SectionError> {
    let q = t.qpd;
    if q.backend != REDPITAYA {
        return Ok(());
    }
    let host = q.host.as_deref().unwrap_or("").trim();
    if host.is_empty() {
        return Err(bad(
            "qpd.host",
            "required when backend = \"redpitaya\" (the board's name or address, e.g. \"rp-f0a1b2.local\" or \"192.168.1.100\")",
        ));
    }
    if host.contains("://") || host.contains(char::is_whitespace) || host.matches(':').count() == 1
    {
        return Err(bad(
            "qpd.host",
            format!(
                "{host:?} is not a host name or address (give the port separately: port = 5000)"
            ),
        ));
    }
    port(q)?;
    if let QpdChannels::Names(_) = q.channels {
        return Err(bad(
            "qpd.channels",
            "input names (\"ai0\"…) are for backend = \"nidaqmx\"; a Red Pitaya's inputs are numbers: { sx = 1, sy = 2, sz = 3 }",
        ));
    }
    q.channels
        .inputs()
        .check()
        .map_err(|(k, m)| bad(&format!("qpd.channels.{k}"), m))?;
    let r = q.sample_rate_hz;
    if !(r.is_finite() && r > 0.0 && r <= BASE_RATE_HZ) {
        return Err(bad(
            "qpd.sample_rate_hz",
            format!("{r} Hz: must be above 0 and at most 125e6 Hz (the board's ADC rate)"),
        ));
    }
    Ok(())
}

/// The Red Pitaya's TCP port: `qpd.port` as a number (default 5000).
pub fn port(q: &QpdConfig) -> Result<u16, SectionError> {
    match q.port.as_deref() {
        None => Ok(DEFAULT_PORT),
        Some(p) => match p.trim().parse::<u16>() {
            Ok(n) if n > 0 => Ok(n),
            _ => Err(bad(
                "qpd.port",
                format!(
                    "{p:?}: the SCPI server's TCP port, a number from 1 to 65535 (Red Pitaya: 5000)"
                ),
            )),
        },
    }
}

/// Red Pitaya driver settings from `[qpd]`.
pub fn options(q: &QpdConfig) -> RedPitayaOptions {
    RedPitayaOptions {
        timeout: Duration::from_millis(q.timeout_ms),
        calibration: q.calibration,
        channels: q.channels.inputs(),
        sample_rate_hz: q.sample_rate_hz,
        gain: q.input_gain,
        sum_floor_v: q.sum_floor,
        ..RedPitayaOptions::default()
    }
}

/// Connect the board `[qpd]` names.
fn open_qpd(t: &Tables) -> Result<Opened<Box<dyn Qpd>>, OpenError> {
    let q = t.qpd;
    let host = q.host.clone().unwrap_or_default();
    let port = port(q)?;
    let qpd = RedPitaya::open(&host, port, options(q))?;
    let description = json!({
        "backend": REDPITAYA,
        "name": qpd.name(),
        "host": host,
        "port": port,
        "address": format!("{host}:{port}"),
        "idn": qpd.idn(),
        "buffer_samples": qpd.buffer_size(),
        "channels": q.channels,
        "input_gain": q.input_gain,
        "sample_rate_hz": qpd.sample_rate(),
        "calibration": q.calibration,
    });
    Ok(Opened {
        device: Box::new(qpd),
        description,
    })
}
