//! The `[stage]`, `[qpd]` and `[raster]` tables of `bfpscope.toml` as the device families read
//! them (each family's `config.rs` checks its keys, builds its driver settings and opens its
//! devices from them), with the small value types they are made of. `config/` owns the file:
//! it parses it once, refuses unknown keys, and hands these tables to the families of
//! `registry.rs`. A leaf of the families: it names none of them.

use super::QpdReading;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// A `[stage]` or `[qpd]` backend of `bfpscope.toml`: a name some family provides
/// ([`Family::stages`], [`Family::qpds`]); each family's folder names its own (`gcs::GCS`).
/// Read from the file through the registry (`registry::config_backend`): a name no family
/// provides is refused, listing those that are.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Backend(pub &'static str);

impl Backend {
    /// The name written in `bfpscope.toml`.
    pub fn as_str(self) -> &'static str {
        self.0
    }
}

impl serde::Serialize for Backend {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.0)
    }
}

/// The simulated instrument's backend (`sim/`): what a file without `[stage]`/`[qpd]` names.
pub const SIMULATED: Backend = Backend("sim");

/// Volts → signal units, per channel (Sx, Sy, Sz): `signal = gain · (volts − offset_v)`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Calibration {
    /// Signal units per volt.
    pub gain: [f64; 3],
    /// Volts read with the beam centred and no sample (dark/centred offset).
    pub offset_v: [f64; 3],
}

impl Default for Calibration {
    fn default() -> Self {
        Self {
            gain: [1.0; 3],
            offset_v: [0.0; 3],
        }
    }
}

impl Calibration {
    /// Convert a volt reading (means and per-sample standard deviations) into a `QpdReading`.
    pub fn apply(&self, volts: [f64; 3], std_v: [f64; 3], n: usize) -> QpdReading {
        let s = |i: usize| self.gain[i] * (volts[i] - self.offset_v[i]);
        let d = |i: usize| self.gain[i].abs() * std_v[i];
        QpdReading {
            sx: s(0),
            sy: s(1),
            sz: s(2),
            sx_std: d(0),
            sy_std: d(1),
            sz_std: d(2),
            n,
            clipped: [0; 3],
        }
    }
}

/// Input range jumper setting (`ACQ:SOUR<n>:GAIN`): LV ±1 V, HV ±20 V.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
pub enum InputGain {
    #[default]
    LV,
    HV,
}

impl InputGain {
    pub fn as_str(self) -> &'static str {
        match self {
            InputGain::LV => "LV",
            InputGain::HV => "HV",
        }
    }
    /// Full scale, volts.
    pub fn full_scale_v(self) -> f64 {
        match self {
            InputGain::LV => 1.0,
            InputGain::HV => 20.0,
        }
    }
}

/// Which fast analog input (1–4) digitises each signal. Sz is optional: a 2-input board has
/// Sx and Sy only, and Sz then reads 0.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChannelMap {
    pub sx: u8,
    pub sy: u8,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sz: Option<u8>,
}

impl Default for ChannelMap {
    fn default() -> Self {
        Self {
            sx: 1,
            sy: 2,
            sz: None,
        }
    }
}

impl ChannelMap {
    /// The inputs in the order Sx, Sy, Sz.
    pub fn inputs(&self) -> [Option<u8>; 3] {
        [Some(self.sx), Some(self.sy), self.sz]
    }

    /// Inputs are 1 to 4 and all different. Err: (signal name, message).
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        let names = ["sx", "sy", "sz"];
        let ins = self.inputs();
        for (i, c) in ins.iter().enumerate() {
            if let Some(c) = c {
                if !(1..=4).contains(c) {
                    return Err((
                        names[i],
                        format!(
                            "input {c}: allowed inputs are 1 and 2 (STEMlab 125-14) or 1 to 4 (its 4-input model)"
                        ),
                    ));
                }
            }
        }
        for i in 0..3 {
            for j in i + 1..3 {
                if let (Some(a), Some(b)) = (ins[i], ins[j]) {
                    if a == b {
                        return Err((
                            names[j],
                            format!(
                                "input {b} is already {}: each signal needs its own input",
                                names[i]
                            ),
                        ));
                    }
                }
            }
        }
        Ok(())
    }
}

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
fn string_or_int<'de, D: serde::Deserializer<'de>>(d: D) -> Result<String, D::Error> {
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

/// The name of axis `i` (0 x, 1 y, else z) of an x/y/z table.
fn xyz(i: usize, [x, y, z]: [&str; 3]) -> &str {
    match i {
        0 => x,
        1 => y,
        _ => z,
    }
}

/// Controller axis identifiers for x, y, z.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AxisMap {
    #[serde(deserialize_with = "string_or_int")]
    pub x: String,
    #[serde(deserialize_with = "string_or_int")]
    pub y: String,
    #[serde(deserialize_with = "string_or_int")]
    pub z: String,
}

impl Default for AxisMap {
    /// An E-727's axes (`SAI?` answers `1 2 3`).
    fn default() -> Self {
        Self {
            x: "1".into(),
            y: "2".into(),
            z: "3".into(),
        }
    }
}

impl AxisMap {
    pub fn get(&self, i: usize) -> &str {
        xyz(i, [&self.x, &self.y, &self.z])
    }
}

/// `stage.ports`: the port of the controller driving each axis, for a stage split across
/// controllers (XY on an E-727, Z on an E-709; or one single-axis controller per axis).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AxisPorts {
    pub x: String,
    pub y: String,
    pub z: String,
}

impl AxisPorts {
    pub fn get(&self, i: usize) -> &str {
        xyz(i, [&self.x, &self.y, &self.z])
    }
}

/// `[stage]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StageConfig {
    pub backend: Backend,
    /// Serial port (`/dev/ttyUSB0`, `/dev/serial/by-id/…`, `COM3`) or `tcp://HOST:50000`, of
    /// the one controller driving x, y, z; for `gcs`, this or `ports`.
    pub port: Option<String>,
    /// Ports per axis for a stage split across controllers (axes on one port are one
    /// controller); for `gcs`, this or `port`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ports: Option<AxisPorts>,
    pub baud: u32,
    /// Reply timeout per command, ms.
    pub timeout_ms: u64,
    /// Longest wait for on-target after a move, ms.
    pub on_target_timeout_ms: u64,
    /// Interval between motion polls after a move, ms (gcs: `#5`, then `ONT?`; kpz101:
    /// `MGMSG_PZ_REQ_OUTPUTPOS`); unset: the backend's default ([`StageConfig::poll_ms`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub poll_ms: Option<u64>,
    /// Poll the end of a move with PI's single-character `#5` (falls back to `ONT?` on a
    /// controller without it); false: always `ONT?`.
    pub motion_status: bool,
    pub axes: AxisMap,
    /// Switch the closed-loop servos on at connect.
    pub servo_on_connect: bool,
    /// Controller position units per µm (1 for PI piezo controllers).
    pub units_per_um: f64,
    /// Extra settle time after each move, s (after on-target for hardware). Default 5 ms;
    /// madlib: 0 (its family's `stage_defaults`: a move ends when the readings stay within
    /// `tolerance_um`).
    pub settle_s: f64,
    /// Ask the controller one axis per query (`POS? 1`, `POS? 2`, …); detected at connect
    /// anyway when a controller answers a several-axis query for the first axis only.
    pub one_axis_per_query: bool,
    /// kpz101: travel of the x, y, z actuators in µm, instead of what each cube reports
    /// (`MGMSG_PZ_REQ_MAXTRAVEL`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub travel_um: Option<[f64; 3]>,
    /// kpz101: position counts for 100 % of the travel (32767 per Thorlabs' document; 65535).
    pub full_scale: u32,
    /// kpz101: on target within this distance, µm.
    pub tolerance_um: f64,
    /// kpz101: zero each cube's strain gauge at connect (`MGMSG_PZ_SET_ZERO`, then wait for
    /// the "zeroed" status bit) when it is not zeroed; the actuators go to their zero first.
    pub zero_at_connect: bool,
    /// kpz101: longest wait for the "zeroed" status bit after `MGMSG_PZ_SET_ZERO`, ms.
    pub zero_timeout_ms: u64,
    /// gcs: the controller's digital output (1…3) wired to the digitiser's external trigger
    /// (a Red Pitaya's DIO0_P): pulsed at the first point of every hardware-timed raster line
    /// (`CTO` generator-trigger mode). Unset: no raster with an externally triggered digitiser.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub trigger_line: Option<u8>,
    /// gcs: servo cycle in s, for a controller that does not answer `SPA? <axis> 0x0E000200`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub servo_cycle_s: Option<f64>,
    /// gcs: points per wave table, for a controller that does not answer `WMS?`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_wave_points: Option<usize>,
    /// gcs: points per data-recorder table, for a controller that does not answer
    /// `SPA? <axis> 0x16000200` / `0x16000300`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_record_points: Option<usize>,
    /// madlib: the library's path (default: the usual names and paths).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub library: Option<std::path::PathBuf>,
    /// madlib: the Nano-Drive's serial number (default: the only one attached).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub serial: Option<i32>,
}

impl Default for StageConfig {
    fn default() -> Self {
        Self {
            backend: SIMULATED,
            port: None,
            ports: None,
            baud: 115_200,
            timeout_ms: 1000,
            on_target_timeout_ms: 5000,
            poll_ms: None,
            motion_status: true,
            axes: AxisMap::default(),
            servo_on_connect: true,
            units_per_um: 1.0,
            settle_s: 0.005,
            one_axis_per_query: false,
            travel_um: None,
            full_scale: 32767,
            tolerance_um: 0.05,
            zero_at_connect: false,
            zero_timeout_ms: 60_000,
            trigger_line: None,
            servo_cycle_s: None,
            max_wave_points: None,
            max_record_points: None,
            library: None,
            serial: None,
        }
    }
}

/// `[qpd]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct QpdConfig {
    pub backend: Backend,
    /// Serial port; required for `scpi` and `kpa101`. For `redpitaya` the TCP port of the
    /// SCPI server (a number, default 5000).
    #[serde(deserialize_with = "string_or_number", default)]
    pub port: Option<String>,
    /// redpitaya: host name or IP address of the board.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub host: Option<String>,
    /// redpitaya: the input (1–4) digitising Sx, Sy and (4-input model) Sz; nidaqmx: the
    /// input names (`sx`, `sy`, `sum` or `q1`…`q4` = `"ai0"`…).
    pub channels: QpdChannels,
    /// redpitaya: nominal QPD sample rate, Hz (a read of n samples covers n / rate seconds).
    pub sample_rate_hz: f64,
    /// redpitaya: input range, "LV" (±1 V) or "HV" (±20 V), as the jumpers are set.
    pub input_gain: InputGain,
    pub baud: u32,
    /// Reply timeout per command, ms (a measurement adds n / sample rate).
    pub timeout_ms: u64,
    /// Ask for standard deviations too (`MEAS:QPD:STAT?`).
    pub statistics: bool,
    /// Volts → signal units.
    pub calibration: Calibration,
    /// kpa101: volts per count of the Sum reading (document: 10/65535).
    pub sum_scale: f64,
    /// kpa101: sign applied to the X difference, 1 or -1.
    pub x_sign: f64,
    /// kpa101: the Sum word is a signed 16-bit number.
    pub signed: bool,
    /// nidaqmx: the library's path (default: the usual names and paths).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub library: Option<std::path::PathBuf>,
    /// nidaqmx: the board's name in NI MAX (`"Dev1"`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub device: Option<String>,
    /// nidaqmx: input range ±V (default 10); scpi: the digitiser's input range ±V (no
    /// default: without it clipping is not counted).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub range_v: Option<f64>,
    /// The sum input (V, before the calibration) below which a pixel is dark (laser off, beam
    /// blocked); default 1 % of the input range; 0 switches the check off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sum_floor: Option<f64>,
    /// nidaqmx: terminal configuration, "diff" (default), "rse", "nrse", "pseudodiff", "default".
    #[serde(skip_serializing_if = "Option::is_none")]
    pub terminal: Option<String>,
    /// nidaqmx: sample rate per channel, Hz (default 800000, the PCI-6120's maximum).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rate_hz: Option<f64>,
}

impl Default for QpdConfig {
    fn default() -> Self {
        Self {
            backend: SIMULATED,
            port: None,
            host: None,
            channels: QpdChannels::default(),
            sample_rate_hz: 100_000.0,
            input_gain: InputGain::LV,
            baud: 115_200,
            timeout_ms: 1000,
            statistics: true,
            calibration: Calibration::default(),
            sum_scale: 10.0 / 65535.0,
            x_sign: 1.0,
            signed: false,
            library: None,
            device: None,
            range_v: None,
            sum_floor: None,
            terminal: None,
            rate_hz: None,
        }
    }
}

/// The axis names of an x/y/z table, in order.
pub const AXIS_NAMES: [&str; 3] = ["x", "y", "z"];

/// `qpd.port`: a serial port path (string) or, for a TCP device, a port number.
fn string_or_number<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<String>, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum V {
        S(String),
        N(i64),
    }
    Ok(Option::<V>::deserialize(d)?.map(|v| match v {
        V::S(s) => s,
        V::N(n) => n.to_string(),
    }))
}

/// The tables a family reads: `[stage]`, `[qpd]` and (the NI board's) `[raster]`.
#[derive(Clone, Copy)]
pub struct Tables<'a> {
    pub stage: &'a StageConfig,
    pub qpd: &'a QpdConfig,
    pub raster: Option<&'a RasterConfig>,
}

/// A bad value in a table: its dotted key (`stage.ports.x`) and what is wrong, naming the
/// value and what is allowed (`config/` adds the file and the line).
#[derive(Debug, Clone, PartialEq)]
pub struct SectionError {
    pub key: String,
    pub message: String,
}

/// A [`SectionError`] at `key`.
pub fn bad(key: &str, message: impl Into<String>) -> SectionError {
    SectionError {
        key: key.into(),
        message: message.into(),
    }
}

/// Refuse the first of `keys` (key, whether it is set) that is set although it applies only to
/// `backend`; `is` says what the device's backend is instead.
pub fn only_for<const N: usize>(
    backend: &str,
    is: &str,
    keys: [(&str, bool); N],
) -> Result<(), SectionError> {
    match keys.into_iter().find(|(_, set)| *set) {
        Some((key, _)) => Err(bad(key, format!("only for backend = \"{backend}\" ({is})"))),
        None => Ok(()),
    }
}

impl StageConfig {
    /// The distinct stage ports (`port`, or those of `ports`), in x, y, z order of first use.
    pub fn distinct_ports(&self) -> Vec<String> {
        let mut out: Vec<String> = Vec::new();
        match (&self.port, &self.ports) {
            (Some(p), _) => out.push(p.clone()),
            (None, Some(ps)) => {
                for i in 0..3 {
                    if !out.iter().any(|p| p == ps.get(i)) {
                        out.push(ps.get(i).to_string());
                    }
                }
            }
            _ => {}
        }
        out
    }
}

impl QpdConfig {
    /// `qpd.port` is given (a QPD on a serial port).
    pub fn require_port(&self) -> Result<(), SectionError> {
        if self.port.as_deref().is_none_or(|p| p.trim().is_empty()) {
            return Err(bad(
                "qpd.port",
                format!(
                    "required when backend = \"{}\" (e.g. \"/dev/ttyUSB1\")",
                    self.backend.as_str()
                ),
            ));
        }
        Ok(())
    }
}
