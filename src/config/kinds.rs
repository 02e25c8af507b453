//! The small types the config's tables are made of, with no rule in them: the device backend
//! (a family's name, read through the registry),
//! the bench's `qpd.channels` and `[raster]` tables (their checks: `bench.rs`; connecting what
//! they name: `connect.rs`). A leaf: `mod.rs`, `bench.rs` and `connect.rs` use it.

use crate::instrument::redpitaya::ChannelMap;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// A device backend: the name of a `[stage]`/`[qpd]` backend some device family provides
/// (`instrument::registry`).
pub use crate::instrument::family::Backend;

/// PCI-6120: the highest sample rate per channel, Hz.
pub const PCI6120_MAX_RATE_HZ: f64 = 800_000.0;
/// PCI-6120: the widest input range, ±V.
pub const PCI6120_MAX_RANGE_V: f64 = 42.0;

/// `qpd.channels`: a Red Pitaya's input numbers (`{ sx = 1, sy = 2, sz = 3 }`) or an NI
/// board's input names (`{ sx = "ai0", sy = "ai1", sum = "ai2" }`, or `q1`…`q4`).
#[derive(Debug, Clone, PartialEq)]
pub enum QpdChannels {
    Inputs(ChannelMap),
    Names(BTreeMap<String, String>),
}

impl Default for QpdChannels {
    fn default() -> Self {
        QpdChannels::Inputs(ChannelMap::default())
    }
}

impl QpdChannels {
    /// The Red Pitaya input numbers (the default map when names were given).
    pub fn inputs(&self) -> ChannelMap {
        match self {
            QpdChannels::Inputs(c) => *c,
            QpdChannels::Names(_) => ChannelMap::default(),
        }
    }
}

impl Serialize for QpdChannels {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            QpdChannels::Inputs(c) => c.serialize(s),
            QpdChannels::Names(m) => m.serialize(s),
        }
    }
}

impl<'de> Deserialize<'de> for QpdChannels {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        let t = toml::Table::deserialize(d)?;
        let strings = t.values().filter(|v| v.is_str()).count();
        if strings == 0 {
            let c = ChannelMap::deserialize(toml::Value::Table(t)).map_err(D::Error::custom)?;
            return Ok(QpdChannels::Inputs(c));
        }
        if strings != t.len() {
            return Err(D::Error::custom(
                "give all inputs as numbers (a Red Pitaya's inputs 1–4) or all as names (an NI board's \"ai0\"…), not both",
            ));
        }
        Ok(QpdChannels::Names(
            t.into_iter()
                .map(|(k, v)| (k, v.as_str().unwrap_or_default().to_string()))
                .collect(),
        ))
    }
}

/// An axis identifier given as a string (`"1"`, `"A"`) or a number (`1`).
pub(super) fn string_or_int<'de, D: serde::Deserializer<'de>>(d: D) -> Result<String, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum V {
        S(String),
        N(i64),
    }
    Ok(match V::deserialize(d)? {
        V::S(s) => s,
        V::N(n) => n.to_string(),
    })
}

/// Per-axis values of `[raster]` (x and y; the fast and slow axes of `scan_xy`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(
    deny_unknown_fields,
    expecting = "a table of per-axis values { x = …, y = … }"
)]
pub struct Xy<T> {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x: Option<T>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y: Option<T>,
}

/// Per-axis NI channel names (`ao`, `position`).
pub type XyNames = Xy<String>;
/// Per-axis numbers (`volts_per_um`, `position_volts_per_um`).
pub type XyNumbers = Xy<f64>;

/// `[raster]`: the NI board's hardware-timed raster.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RasterConfig {
    pub backend: Backend,
    /// NI analog outputs wired to the Nano-Drive's external inputs.
    #[serde(default)]
    pub ao: XyNames,
    /// Volts per µm of each external input (0–10 V over the axis's calibrated range).
    #[serde(default)]
    pub volts_per_um: XyNumbers,
    /// NI analog inputs wired to the Nano-Drive's sensor-monitor outputs.
    #[serde(default)]
    pub position: XyNames,
    /// Volts per µm of each sensor-monitor output.
    #[serde(default)]
    pub position_volts_per_um: XyNumbers,
    /// How the Nano-Drive combines its external inputs with the USB command: `"sum"` (added,
    /// as MCL documents it; the default) or `"replace"` (the controller follows the external
    /// input alone while it is driven).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub external_input: Option<String>,
}
