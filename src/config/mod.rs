//! The instrument part of `bfpscope.toml`: backends and ports, serial settings, axis map,
//! settle time, QPD calibration, and the `[safety]` table (soft limits, step and speed limits;
//! defined and enforced by `acquire::limits`, parsed and validated here with the rest of the
//! file).
//!
//! ```toml
//! [stage]
//! backend = "gcs"               # "sim" (default) | "gcs"
//! port = "/dev/ttyUSB0"        # or "tcp://192.168.0.10:50000"; or, split across controllers:
//!                               # ports = { x = "/dev/ttyUSB0", y = "/dev/ttyUSB0", z = "/dev/ttyUSB2" }
//! baud = 115200
//! axes = { x = "1", y = "2", z = "3" }   # checked against the controller's SAI? at connect
//!
//! [qpd]
//! backend = "scpi"              # "sim" (default) | "scpi" | "kpa101" | "redpitaya"
//! port = "/dev/ttyUSB1"
//! calibration = { gain = [0.5, 0.5, 0.25], offset_v = [0.0, 0.0, 0.0] }
//! # a Red Pitaya STEMlab instead (TCP, SCPI server port 5000):
//! # backend = "redpitaya"
//! # host = "rp-f0a1b2.local"
//! # port = 5000
//! # channels = { sx = 1, sy = 2, sz = 3 }   # inputs IN1..IN4; sz only on the 4-input model
//! # sample_rate_hz = 100000.0              # nominal QPD rate: a read of n samples lasts n / rate
//! # input_gain = "LV"                      # LV ±1 V | HV ±20 V, as the jumpers are set
//!
//! [safety]                     # enforced by the scan engine for every backend
//! soft_limits = { x = [10.0, 90.0], y = [10.0, 90.0], z = [2.0, 18.0] }   # µm
//! max_step_um = 10.0            # largest pixel pitch of a scan, µm
//! max_speed_um_s = 500.0        # fastest a scan may move the stage, µm/s
//! ```
//!
//! With no file, everything is simulated. This module owns the whole file: besides the
//! tables above, `[sandbox]`, `[session]` and `[optics]` ([`tables`]). An unknown table or key,
//! anywhere, is an error naming the file, the key path (`stage.baud`), the line and the nearest
//! known name: a misspelled `[saftey]` must not drop the soft limits silently, nor a `[Stage]`
//! start the simulator in place of the hardware it names. The legacy `[limits]` table and
//! `stage.max_speed_um_s` are refused with their `[safety]` equivalent.

pub mod bench;
pub mod connect;
pub mod kinds;
pub mod tables;

pub use tables::{OpticsConfig, Sandbox, SessionConfig};

pub use kinds::{Backend, QpdChannels, RasterConfig};

use crate::acquire::limits::{SafetyConfig, SoftLimits};
use crate::instrument::gcs::GcsOptions;
use crate::instrument::link::TCP_PREFIX;
use crate::instrument::redpitaya::{InputGain, RedPitayaOptions};
use crate::instrument::scpi::{Calibration, ScpiOptions};
use crate::instrument::{
    gcs::GCS, redpitaya::REDPITAYA, scpi::SCPI, sim::SIM, thorlabs::KPA101, thorlabs::KPZ101,
};
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::time::Duration;

/// The config file looked for in the working directory.
pub const DEFAULT_FILE: &str = "bfpscope.toml";
/// Environment variable naming a config file (takes precedence over `./bfpscope.toml`).
pub const ENV_VAR: &str = "BFPSCOPE_CONFIG";

/// Longest reply timeout a device may be given, ms (one hour): `[stage]`/`[qpd]` `timeout_ms`
/// and `connect(#{timeout_ms})`.
pub const MAX_TIMEOUT_MS: u64 = 3_600_000;

/// Highest serial baud rate `connect(#{baud, stage_baud, qpd_baud})` accepts.
pub const MAX_BAUD: u32 = 4_000_000;

/// A config problem: where (file, key path, line) and what.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{origin}: {key}: {message}{}", line.map(|l| format!(" (line {l})")).unwrap_or_default())]
pub struct ConfigError {
    /// The file (or `"<string>"`, `"defaults"`).
    pub origin: String,
    /// Dotted key path, e.g. `stage.baud` (empty for the whole file).
    pub key: String,
    /// 1-based line in the file, when known.
    pub line: Option<usize>,
    pub message: String,
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
    #[serde(deserialize_with = "kinds::string_or_int")]
    pub x: String,
    #[serde(deserialize_with = "kinds::string_or_int")]
    pub y: String,
    #[serde(deserialize_with = "kinds::string_or_int")]
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
            backend: SIM,
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

impl StageConfig {
    /// The defaults of the family providing this stage (`instrument::registry`).
    pub fn family_defaults(&self) -> crate::instrument::registry::StageDefaults {
        crate::instrument::registry::by_stage(self.backend.as_str())
            .map_or(crate::instrument::registry::STAGE_DEFAULTS, |f| {
                f.stage_defaults
            })
    }

    /// The motion polling interval in force, ms: `poll_ms` when set, else the default of
    /// the stage's family (`Family::stage_defaults`: gcs 1, kpz101 10, madlib 0, else 5).
    pub fn poll_ms(&self) -> u64 {
        self.poll_ms.unwrap_or(self.family_defaults().poll_ms)
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
            backend: SIM,
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

/// The whole `bfpscope.toml`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    #[serde(default)]
    pub stage: StageConfig,
    #[serde(default)]
    pub qpd: QpdConfig,
    /// `[safety]`: soft limits, step and speed limits (`acquire::limits`).
    #[serde(default)]
    pub safety: SafetyConfig,
    /// `[raster]`: the NI board's hardware-timed raster (`config/bench.rs`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub raster: Option<RasterConfig>,
    /// `[sandbox]`: the script's limits.
    #[serde(default)]
    pub sandbox: Sandbox,
    /// `[session]`: where scans go.
    #[serde(default)]
    pub session: SessionConfig,
    /// `[optics]`: the optics the session starts with.
    #[serde(default, skip_serializing_if = "OpticsConfig::is_empty")]
    pub optics: OpticsConfig,
}

/// The top-level tables of `bfpscope.toml`.
pub const TABLES: [&str; 7] = [
    "stage", "qpd", "safety", "sandbox", "session", "optics", "raster",
];

const AXIS_NAMES: [&str; 3] = ["x", "y", "z"];

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

/// The key path and 1-based line at byte `offset` of a TOML text, by tracking `[table]`
/// headers and `key =` lines (good enough for error messages).
fn key_path_at(src: &str, offset: usize) -> (String, usize) {
    let mut table = String::new();
    let mut key = String::new();
    let mut start = 0usize;
    for (n, line) in src.split_inclusive('\n').enumerate() {
        let t = line.trim();
        if let Some(header) = table_header(t) {
            table = header;
            key.clear();
        } else if let Some((k, _)) = t.split_once('=') {
            if !t.starts_with('#') {
                key = k.trim().trim_matches('"').to_string();
            }
        }
        let end = start + line.len();
        if offset < end || end == src.len() {
            let path = match (table.is_empty(), key.is_empty()) {
                (_, true) => table.clone(),
                (true, false) => key.clone(),
                (false, false) => format!("{table}.{key}"),
            };
            return (path, n + 1);
        }
        start = end;
    }
    (String::new(), 1)
}

/// `[a.b]` / `[[a.b]]` → `a.b`; None for other lines (including arrays such as `[1, 2],`).
fn table_header(line: &str) -> Option<String> {
    let inner = line.strip_prefix('[')?;
    let inner = inner.strip_prefix('[').unwrap_or(inner);
    let (inner, rest) = inner.split_once(']')?;
    let rest = rest.trim_start_matches(']').trim();
    if !(rest.is_empty() || rest.starts_with('#')) {
        return None;
    }
    let inner = inner.trim();
    let first = inner.chars().next()?;
    let ok = !first.is_ascii_digit()
        && first != '-'
        && inner
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "_-.\" ".contains(c));
    ok.then(|| {
        inner
            .split('.')
            .map(|s| s.trim().trim_matches('"'))
            .collect::<Vec<_>>()
            .join(".")
    })
}

fn err(key: &str, message: impl Into<String>) -> ConfigError {
    ConfigError {
        origin: String::new(),
        key: key.into(),
        line: None,
        message: message.into(),
    }
}

/// serde's `unknown field `saftey`, expected one of `stage`, …` with the nearest known name
/// first: `unknown field `saftey`; did you mean `safety`? (known: `stage`, …)`. Nearest: within
/// two edits (a third of the word's length for long words), or a known name the word begins
/// (`max_step` → `max_step_um`); words under three letters get no guess. Without a guess, and
/// for other messages, serde's text is returned unchanged.
fn with_nearest(message: &str) -> String {
    let Some(rest) = message.strip_prefix("unknown field `") else {
        return message.to_string();
    };
    let Some((word, tail)) = rest.split_once('`') else {
        return message.to_string();
    };
    let known: Vec<&str> = tail.split('`').skip(1).step_by(2).collect();
    let w = word.to_lowercase();
    let limit = (w.chars().count() / 3).max(2);
    let nearest = known
        .iter()
        .filter_map(|k| {
            let kl = k.to_lowercase();
            let d = strsim::damerau_levenshtein(&w, &kl);
            if d <= limit {
                Some((d, *k))
            } else if kl.starts_with(&w) {
                Some((limit + 1, *k))
            } else {
                None
            }
        })
        .min()
        .filter(|_| w.chars().count() >= 3);
    match nearest {
        Some((_, k)) => {
            let list = known
                .iter()
                .map(|k| format!("`{k}`"))
                .collect::<Vec<_>>()
                .join(", ");
            format!("unknown field `{word}`; did you mean `{k}`? (known: {list})")
        }
        None => message.to_string(),
    }
}

impl Config {
    /// Parse and validate TOML text. `origin` names the text in messages (a file path).
    pub fn from_toml_str(text: &str, origin: &str) -> Result<Config, ConfigError> {
        // `[stage] max_speed_um_s` moved to `[safety]`: say so rather than "unknown field".
        if let Ok(raw) = toml::from_str::<toml::Table>(text) {
            if let Some(old) = raw.get("limits") {
                return Err(ConfigError {
                    origin: origin.into(),
                    key: "limits".into(),
                    line: find_table_line(text, "limits").or_else(|| find_key_line(text, "limits")),
                    message: legacy_limits_message(old),
                });
            }
            if let Some(v) = raw.get("stage").and_then(|s| s.get("max_speed_um_s")) {
                return Err(ConfigError {
                    origin: origin.into(),
                    key: "stage.max_speed_um_s".into(),
                    line: find_key_line(text, "stage.max_speed_um_s"),
                    message: format!(
                        "moved to [safety]: write `max_speed_um_s = {v}` in [safety] (enforced by the scan engine \
                         for every backend)"
                    ),
                });
            }
        }
        let mut cfg: Config = toml::from_str(text).map_err(|e| {
            let (key, line) = match e.span() {
                Some(span) => {
                    let (k, l) = key_path_at(text, span.start);
                    (k, Some(l))
                }
                None => (String::new(), None),
            };
            ConfigError {
                origin: origin.into(),
                key,
                line,
                message: with_nearest(e.message().trim()),
            }
        })?;
        // A family's own settle time (a Nano-Drive is settled on its readings: none after
        // them) unless the file asks for one.
        let settle_given = toml::from_str::<toml::Table>(text)
            .ok()
            .is_some_and(|r| r.get("stage").and_then(|s| s.get("settle_s")).is_some());
        if let (Some(s), false) = (cfg.stage.family_defaults().settle_s, settle_given) {
            cfg.stage.settle_s = s;
        }
        cfg.validate().map_err(|mut e| {
            e.origin = origin.into();
            e.line = find_key_line(text, &e.key).or_else(|| find_table_line(text, &e.key));
            e
        })?;
        Ok(cfg)
    }

    /// Read, parse and validate a config file.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let origin = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| ConfigError {
            origin: origin.clone(),
            key: String::new(),
            line: None,
            message: format!("cannot read: {e}"),
        })?;
        Self::from_toml_str(&text, &origin)
    }

    /// TOML text of this config.
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_else(|e| format!("# cannot serialise config: {e}\n"))
    }

    /// True when both devices are simulated.
    pub fn is_simulated(&self) -> bool {
        self.stage.backend == SIM && self.qpd.backend == SIM
    }

    /// Check values and combinations. Errors name the key path.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.validate_backends()?;
        self.validate_devices()?;
        self.validate_links()?;
        self.validate_axes()?;
        self.validate_stage_numbers()?;
        self.validate_qpd_numbers()?;
        self.validate_bench()?;
        self.safety.validate().map_err(|(k, m)| err(&k, m))?;
        self.sandbox.validate().map_err(|(k, m)| err(&k, m))?;
        self.optics.resolve().map_err(|(k, m)| err(&k, m))?;
        if let Some(d) = &self.session.data_dir {
            if d.trim().is_empty() {
                return Err(err(
                    "session.data_dir",
                    "\"\": must name a folder (or leave the key out for ./bfpscope_data/YYYY-MM-DD/)",
                ));
            }
        }
        Ok(())
    }

    /// The `[stage]` and `[qpd]` backends: each the kind its family provides, both simulated or both hardware.
    fn validate_backends(&self) -> Result<(), ConfigError> {
        let s = &self.stage;
        let q = &self.qpd;
        // which backend is a stage's and which a QPD's: the device families say
        for (key, b, qpd, other) in [
            ("stage.backend", s.backend, false, "QPD"),
            ("qpd.backend", q.backend, true, "stage"),
        ] {
            let allowed = crate::instrument::registry::config_backends(qpd);
            if !allowed.contains(&b.as_str()) {
                let listed: Vec<String> = allowed.iter().map(|b| format!("{b:?}")).collect();
                return Err(err(
                    key,
                    format!(
                        "\"{}\" is a {other} backend; allowed for a {}: {}",
                        b.as_str(),
                        if qpd { "QPD" } else { "stage" },
                        listed.join(", ")
                    ),
                ));
            }
        }
        if (s.backend == SIM) != (q.backend == SIM) {
            return Err(err(
                "qpd.backend",
                format!(
                    "stage is \"{}\" but qpd is \"{}\": use both simulated or both hardware (the simulated QPD \
                     images the simulated stage's scene)",
                    s.backend.as_str(),
                    q.backend.as_str()
                ),
            ));
        }
        Ok(())
    }

    /// The rules of each backend: ports, the KPZ101 and KPA101 settings, the Red Pitaya's.
    fn validate_devices(&self) -> Result<(), ConfigError> {
        let s = &self.stage;
        let q = &self.qpd;
        if s.backend == GCS {
            self.validate_stage_ports()?;
        }
        if s.backend == KPZ101 {
            self.validate_kpz101()?;
        }
        if matches!(q.backend, SCPI | KPA101)
            && q.port.as_deref().is_none_or(|p| p.trim().is_empty())
        {
            return Err(err(
                "qpd.port",
                format!(
                    "required when backend = \"{}\" (e.g. \"/dev/ttyUSB1\")",
                    q.backend.as_str()
                ),
            ));
        }
        if q.backend == REDPITAYA {
            self.validate_redpitaya()?;
        }
        if q.backend == KPA101 {
            if !(q.x_sign == 1.0 || q.x_sign == -1.0) {
                return Err(err(
                    "qpd.x_sign",
                    format!("{}: allowed values are 1 and -1", q.x_sign),
                ));
            }
            if !(q.sum_scale.is_finite() && q.sum_scale > 0.0) {
                return Err(err(
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
        }
        if matches!(s.backend, GCS | KPZ101) && q.backend != REDPITAYA {
            if let Some(qp) = &q.port {
                if self.stage_ports().iter().any(|p| p == qp) {
                    return Err(err(
                        "qpd.port",
                        format!("{qp:?}: the stage and the QPD cannot share one port"),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Baud rates and timeouts.
    fn validate_links(&self) -> Result<(), ConfigError> {
        let s = &self.stage;
        let q = &self.qpd;
        for (key, v) in [("stage.baud", s.baud), ("qpd.baud", q.baud)] {
            if v == 0 {
                return Err(err(key, "must be a positive baud rate (e.g. 115200)"));
            }
        }
        for (key, v) in [
            ("stage.timeout_ms", s.timeout_ms),
            ("stage.on_target_timeout_ms", s.on_target_timeout_ms),
            // a value given must be ≥ 1 ms; a backend's default may be 0 (Madlib: back to back)
            ("stage.poll_ms", s.poll_ms.unwrap_or(1)),
            ("stage.zero_timeout_ms", s.zero_timeout_ms),
            ("qpd.timeout_ms", q.timeout_ms),
        ] {
            if v == 0 || v > MAX_TIMEOUT_MS {
                return Err(err(
                    key,
                    format!("{v} ms: must be between 1 ms and one hour"),
                ));
            }
        }
        Ok(())
    }

    /// `stage.axes`: controller axis identifiers, different on one controller.
    fn validate_axes(&self) -> Result<(), ConfigError> {
        let s = &self.stage;
        let axes = [&s.axes.x, &s.axes.y, &s.axes.z];
        for (i, a) in axes.iter().enumerate() {
            if a.is_empty() || a.contains(char::is_whitespace) || a.contains('=') {
                return Err(err(
                    &format!("stage.axes.{}", AXIS_NAMES[i]),
                    format!("{a:?} is not a controller axis identifier"),
                ));
            }
        }
        // axes on one controller (one port) must differ
        let port_of = |i: usize| match &s.ports {
            Some(p) => p.get(i).to_string(),
            None => s.port.clone().unwrap_or_default(),
        };
        for i in 0..3 {
            for j in i + 1..3 {
                if axes[i] == axes[j] && port_of(i) == port_of(j) {
                    return Err(err(
                        "stage.axes",
                        format!(
                            "{} and {} are both {:?} on one controller: x, y and z must be different \
                             controller axes (the identifiers `SAI?` lists)",
                            AXIS_NAMES[i], AXIS_NAMES[j], axes[i]
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    /// The stage's numbers: units, settle time, trigger line, servo cycle, table sizes.
    fn validate_stage_numbers(&self) -> Result<(), ConfigError> {
        let s = &self.stage;
        if !(s.units_per_um.is_finite() && s.units_per_um > 0.0) {
            return Err(err("stage.units_per_um", "must be a positive number"));
        }
        if !(s.settle_s.is_finite() && (0.0..=60.0).contains(&s.settle_s)) {
            return Err(err("stage.settle_s", "must be between 0 and 60 s"));
        }
        if let Some(l) = s.trigger_line {
            if !(1..=3).contains(&l) {
                return Err(err(
                    "stage.trigger_line",
                    format!(
                        "{l}: the controller's digital output wired to the digitiser's trigger, 1, 2 or 3 (OUT1…OUT3, `CTO`)"
                    ),
                ));
            }
        }
        if let Some(c) = s.servo_cycle_s {
            if !(c.is_finite() && c > 0.0 && c <= 0.1) {
                return Err(err(
                    "stage.servo_cycle_s",
                    format!("{c}: the servo cycle must be between 0 and 0.1 s (E-727: 50e-6)"),
                ));
            }
        }
        for (key, v) in [
            ("stage.max_wave_points", s.max_wave_points),
            ("stage.max_record_points", s.max_record_points),
        ] {
            if v == Some(0) {
                return Err(err(key, "0: must be a positive number of points"));
            }
        }
        Ok(())
    }

    /// The QPD's numbers: calibration, sum floor, input range.
    fn validate_qpd_numbers(&self) -> Result<(), ConfigError> {
        let q = &self.qpd;
        for i in 0..3 {
            let g = q.calibration.gain[i];
            if !(g.is_finite() && g != 0.0) {
                return Err(err(
                    "qpd.calibration.gain",
                    format!("channel {i}: {g} must be finite and nonzero"),
                ));
            }
            if !q.calibration.offset_v[i].is_finite() {
                return Err(err("qpd.calibration.offset_v", "must be finite"));
            }
        }
        if let Some(f) = q.sum_floor {
            if q.backend == SIM {
                return Err(err(
                    "qpd.sum_floor",
                    format!("{f}: the simulated QPD has no sum input to check; a scene's `detector_range` effect sets the simulator's floor (`sum_floor`)"),
                ));
            }
            if !(f.is_finite() && f >= 0.0) {
                return Err(err(
                    "qpd.sum_floor",
                    format!("{f}: the sum input's floor in V, 0 (no check) or above"),
                ));
            }
        }
        if q.backend == SCPI {
            if let Some(r) = q.range_v {
                if !(r.is_finite() && r > 0.0) {
                    return Err(err(
                        "qpd.range_v",
                        format!("{r}: the digitiser's input range ±V, above 0"),
                    ));
                }
            }
        }
        Ok(())
    }

    /// The safety rules in force before narrowing to a stage's travel range.
    pub fn soft_limits(&self) -> SoftLimits {
        self.safety.limits()
    }

    /// `stage.port` and `stage.ports`: one of the two, each port `tcp://HOST:PORT` or a
    /// serial path.
    fn validate_stage_ports(&self) -> Result<(), ConfigError> {
        let s = &self.stage;
        match (&s.port, &s.ports) {
            (Some(p), Some(ps)) => {
                return Err(err(
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
                return Err(err(
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
                return Err(err(
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
                    return Err(err(
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

    /// `kpz101`: one cube per axis, so `stage.ports` with three different serial ports.
    fn validate_kpz101(&self) -> Result<(), ConfigError> {
        let s = &self.stage;
        let Some(ps) = &s.ports else {
            return Err(err(
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
            return Err(err(
                "stage.port",
                format!(
                    "{p:?}: with backend = \"kpz101\" give stage.ports only (one cube per axis)"
                ),
            ));
        }
        for i in 0..3 {
            let p = ps.get(i);
            let key = format!("stage.ports.{}", AXIS_NAMES[i]);
            if p.trim().is_empty() || p.starts_with(TCP_PREFIX) {
                return Err(err(
                    &key,
                    format!("{p:?}: a KPZ101 is a USB-serial device: allowed is a serial port (e.g. \"/dev/ttyUSB0\")"),
                ));
            }
            for j in 0..i {
                if ps.get(j) == p {
                    return Err(err(
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
            return Err(err(
                "stage.full_scale",
                format!(
                    "{}: allowed values are 32767 (Thorlabs' document) and 65535",
                    s.full_scale
                ),
            ));
        }
        if !(s.tolerance_um.is_finite() && s.tolerance_um > 0.0) {
            return Err(err(
                "stage.tolerance_um",
                format!("{}: must be a positive distance in µm", s.tolerance_um),
            ));
        }
        if let Some(t) = s.travel_um {
            for i in 0..3 {
                if !(t[i].is_finite() && t[i] > 0.0 && t[i] <= 6553.5) {
                    return Err(err(
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

    /// Driver settings for the KPZ101 cubes.
    pub fn kpz_options(&self) -> crate::instrument::thorlabs::kpz101::KpzOptions {
        let s = &self.stage;
        crate::instrument::thorlabs::kpz101::KpzOptions {
            timeout: Duration::from_millis(s.timeout_ms),
            on_target_timeout: Duration::from_millis(s.on_target_timeout_ms),
            poll_interval: Duration::from_millis(s.poll_ms()),
            tolerance_um: s.tolerance_um,
            travel_um: None,
            full_scale: s.full_scale as u16,
            rtscts: true,
            zero_at_connect: s.zero_at_connect,
            zero_timeout: Duration::from_millis(s.zero_timeout_ms),
        }
    }

    /// Driver settings for the KPA101.
    pub fn kpa_options(&self) -> crate::instrument::thorlabs::kpa101::KpaOptions {
        let q = &self.qpd;
        crate::instrument::thorlabs::kpa101::KpaOptions {
            timeout: Duration::from_millis(q.timeout_ms),
            calibration: q.calibration,
            sum_scale: q.sum_scale,
            x_sign: q.x_sign,
            signed: q.signed,
            rtscts: true,
            sum_floor_v: q.sum_floor,
        }
    }

    /// The distinct stage ports, in x, y, z order of first use (empty unless `gcs`).
    pub fn stage_ports(&self) -> Vec<String> {
        let s = &self.stage;
        let mut out: Vec<String> = Vec::new();
        match (&s.port, &s.ports) {
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

    /// Driver settings for the GCS stage on one controller (all three axes).
    pub fn gcs_options(&self) -> GcsOptions {
        let s = &self.stage;
        GcsOptions {
            axes: [0, 1, 2].map(|i| Some(s.axes.get(i).to_string())),
            timeout: Duration::from_millis(s.timeout_ms),
            on_target_timeout: Duration::from_millis(s.on_target_timeout_ms),
            poll_interval: Duration::from_millis(s.poll_ms()),
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
    pub fn gcs_controllers(&self) -> Vec<(String, GcsOptions)> {
        let base = self.gcs_options();
        match &self.stage.ports {
            None => vec![(self.stage.port.clone().unwrap_or_default(), base)],
            Some(ps) => self
                .stage_ports()
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

    /// Driver settings for the SCPI QPD.
    /// `[qpd]` for a Red Pitaya: `host` required (a name or address, without a port), `port`
    /// a TCP port number, the channel map inputs 1–4 and different, a positive sample rate up
    /// to the board's 125 MHz.
    fn validate_redpitaya(&self) -> Result<(), ConfigError> {
        let q = &self.qpd;
        let host = q.host.as_deref().unwrap_or("").trim();
        if host.is_empty() {
            return Err(err(
                "qpd.host",
                "required when backend = \"redpitaya\" (the board's name or address, e.g. \"rp-f0a1b2.local\" or \"192.168.1.100\")",
            ));
        }
        if host.contains("://")
            || host.contains(char::is_whitespace)
            || host.matches(':').count() == 1
        {
            return Err(err(
                "qpd.host",
                format!("{host:?} is not a host name or address (give the port separately: port = 5000)"),
            ));
        }
        self.redpitaya_port()?;
        if let QpdChannels::Names(_) = q.channels {
            return Err(err(
                "qpd.channels",
                "input names (\"ai0\"…) are for backend = \"nidaqmx\"; a Red Pitaya's inputs are numbers: { sx = 1, sy = 2, sz = 3 }",
            ));
        }
        q.channels
            .inputs()
            .check()
            .map_err(|(k, m)| err(&format!("qpd.channels.{k}"), m))?;
        let r = q.sample_rate_hz;
        if !(r.is_finite() && r > 0.0 && r <= crate::instrument::redpitaya::BASE_RATE_HZ) {
            return Err(err(
                "qpd.sample_rate_hz",
                format!("{r} Hz: must be above 0 and at most 125e6 Hz (the board's ADC rate)"),
            ));
        }
        Ok(())
    }

    /// The Red Pitaya's TCP port: `qpd.port` as a number (default 5000).
    pub fn redpitaya_port(&self) -> Result<u16, ConfigError> {
        match self.qpd.port.as_deref() {
            None => Ok(crate::instrument::redpitaya::DEFAULT_PORT),
            Some(p) => match p.trim().parse::<u16>() {
                Ok(n) if n > 0 => Ok(n),
                _ => Err(err(
                    "qpd.port",
                    format!("{p:?}: the SCPI server's TCP port, a number from 1 to 65535 (Red Pitaya: 5000)"),
                )),
            },
        }
    }

    /// Red Pitaya driver settings from `[qpd]`.
    pub fn redpitaya_options(&self) -> RedPitayaOptions {
        RedPitayaOptions {
            timeout: Duration::from_millis(self.qpd.timeout_ms),
            calibration: self.qpd.calibration,
            channels: self.qpd.channels.inputs(),
            sample_rate_hz: self.qpd.sample_rate_hz,
            gain: self.qpd.input_gain,
            sum_floor_v: self.qpd.sum_floor,
            ..RedPitayaOptions::default()
        }
    }

    pub fn scpi_options(&self) -> ScpiOptions {
        ScpiOptions {
            timeout: Duration::from_millis(self.qpd.timeout_ms),
            calibration: self.qpd.calibration,
            statistics: self.qpd.statistics,
            range_v: self.qpd.range_v,
            sum_floor_v: self.qpd.sum_floor,
            ..ScpiOptions::default()
        }
    }
}

/// The message for a legacy `[limits]` table: its `[safety]` equivalent, spelled out.
fn legacy_limits_message(old: &toml::Value) -> String {
    let mut axes = vec![];
    let mut rest = vec![];
    if let Some(t) = old.as_table() {
        for (k, v) in t {
            match k.as_str() {
                "x" | "y" | "z" => axes.push(format!("{k} = {v}")),
                _ => rest.push(format!("{k} = {v}")),
            }
        }
    }
    let mut s = String::from("the [limits] table is now [safety] (same meanings; max_step_um is the largest pixel pitch of a scan): write [safety]");
    if !axes.is_empty() {
        s.push_str(&format!(" soft_limits = {{ {} }}", axes.join(", ")));
    }
    for r in rest {
        s.push_str(&format!(", {r}"));
    }
    s
}

/// Line of the `[table]` header for `key` (validation errors about a whole table).
fn find_table_line(text: &str, key: &str) -> Option<usize> {
    text.lines()
        .position(|l| table_header(l.trim()).as_deref() == Some(key))
        .map(|n| n + 1)
}

/// Line where `key` (a dotted path) is set, for validation errors: a `k = …` line whose
/// table path plus `k` is `key` or a prefix of it (inline tables such as `axes = { x = … }`).
fn find_key_line(text: &str, key: &str) -> Option<usize> {
    if key.is_empty() {
        return None;
    }
    let mut table = String::new();
    for (n, line) in text.lines().enumerate() {
        let t = line.trim();
        if let Some(h) = table_header(t) {
            table = h;
            continue;
        }
        if t.starts_with('#') {
            continue;
        }
        if let Some((k, _)) = t.split_once('=') {
            let k = k.trim().trim_matches('"');
            let path = if table.is_empty() {
                k.to_string()
            } else {
                format!("{table}.{k}")
            };
            if key == path || key.starts_with(&format!("{path}.")) {
                return Some(n + 1);
            }
        }
    }
    None
}

#[cfg(test)]
mod tests;
