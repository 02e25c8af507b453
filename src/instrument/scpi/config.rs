//! The SCPI digitiser's part of `bfpscope.toml` (`[qpd] backend = "scpi"`): its checks, its
//! driver settings and its opening with the description scans record.

use super::{ScpiOptions, ScpiQpd, SCPI};
use crate::instrument::family::{Family, Open, OpenError, Opened, Section};
use crate::instrument::tables::{bad, QpdConfig, SectionError, Tables};
use crate::instrument::Qpd;
use serde_json::json;
use std::time::Duration;

/// The family, as `instrument::registry` lists it: its names, `connect` keys, defaults,
/// section and help.
pub const FAMILY: Family = Family {
    qpds: &[SCPI.0],
    keys: &["qpd_port", "baud", "qpd_baud", "timeout_ms"],
    section: Section::qpd(validate, open_qpd),
    ..Family::new("scpi", "hardware", Open::config("gcs", "scpi"))
};

/// A SCPI QPD needs its serial port; its input range, when given, is above 0.
fn validate(t: &Tables) -> Result<(), SectionError> {
    let q = t.qpd;
    if q.backend != SCPI {
        return Ok(());
    }
    q.require_port()?;
    if let Some(r) = q.range_v {
        if !(r.is_finite() && r > 0.0) {
            return Err(bad(
                "qpd.range_v",
                format!("{r}: the digitiser's input range ±V, above 0"),
            ));
        }
    }
    Ok(())
}

/// Driver settings for the SCPI QPD.
pub fn options(q: &QpdConfig) -> ScpiOptions {
    ScpiOptions {
        timeout: Duration::from_millis(q.timeout_ms),
        calibration: q.calibration,
        statistics: q.statistics,
        range_v: q.range_v,
        sum_floor_v: q.sum_floor,
        ..ScpiOptions::default()
    }
}

/// Open the SCPI digitiser on `[qpd] port`.
fn open_qpd(t: &Tables) -> Result<Opened<Box<dyn Qpd>>, OpenError> {
    let q = t.qpd;
    let port = q.port.clone().unwrap_or_default();
    let qpd = ScpiQpd::open(&port, q.baud, options(q))?;
    let description = json!({
        "backend": SCPI,
        "name": qpd.name(),
        "port": port,
        "baud": q.baud,
        "idn": qpd.idn(),
        "sample_rate_hz": qpd.sample_rate(),
        "calibration": q.calibration,
    });
    Ok(Opened {
        device: Box::new(qpd),
        description,
    })
}
